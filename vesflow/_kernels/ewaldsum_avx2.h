/* The real-space sum of ewaldsum.h on CPUs with AVX2 and FMA (the VF_PATH_AVX2 path): the
 * arithmetic of vf_ewald_real_avx512 on 4 lanes (blocks of 4 rows of a range, which read at
 * most 3 rows past its end: within the layout's VF_BLOCK - 1), with 1/r from pairsum_avx2.h's
 * vf_rsqrt4_or_0, exp by the reduction and polynomial of vf_exp_nonpos (n by the 1.5 2^52
 * shift, 2^n from the exponent bits), erfcx by vf_erfcx_poly's split, and one division per 4
 * pairs (1/((z + K)(1 + z))). */
#ifndef VESFLOW_EWALDSUM_AVX2_H
#define VESFLOW_EWALDSUM_AVX2_H
#define VF_S4(c) _mm256_set1_pd(c)

/* exp(x), -700 <= x <= 0 (smaller x clamped), 4 lanes */
VF_AVX2_AI __m256d vf_exp4(__m256d x)
{
    x = _mm256_max_pd(x, VF_S4(-700.0));
    const __m256d shift = VF_S4(6755399441055744.0);
    __m256d kd = _mm256_fmadd_pd(x, VF_S4(1.4426950408889634074), shift);
    const __m256i ki = _mm256_castpd_si256(kd);               /* n in the low bits */
    kd = _mm256_sub_pd(kd, shift);
    __m256d s = _mm256_fnmadd_pd(kd, VF_S4(6.93147180369123816490e-01), x);
    s = _mm256_fnmadd_pd(kd, VF_S4(1.90821492927058770002e-10), s);
    const __m256d s2 = _mm256_mul_pd(s, s);
    __m256d pe = _mm256_fmadd_pd(VF_S4(2.08767569878680989792e-09), s2, VF_S4(2.75573192239858906526e-07));
    __m256d po = _mm256_fmadd_pd(VF_S4(2.50521083854417187751e-08), s2, VF_S4(2.75573192239858906526e-06));
    pe = _mm256_fmadd_pd(pe, s2, VF_S4(2.48015873015873015873e-05));
    po = _mm256_fmadd_pd(po, s2, VF_S4(1.98412698412698412698e-04));
    pe = _mm256_fmadd_pd(pe, s2, VF_S4(1.38888888888888888889e-03));
    po = _mm256_fmadd_pd(po, s2, VF_S4(8.33333333333333333333e-03));
    pe = _mm256_fmadd_pd(pe, s2, VF_S4(4.16666666666666666667e-02));
    po = _mm256_fmadd_pd(po, s2, VF_S4(1.66666666666666666667e-01));
    pe = _mm256_fmadd_pd(pe, s2, VF_S4(0.5));
    po = _mm256_fmadd_pd(po, s2, VF_S4(1.0));
    pe = _mm256_fmadd_pd(pe, s2, VF_S4(1.0));
    /* 2^n: (n + 1023) << 52 (the shift drops the high bits of the shifted constant) */
    const __m256i eb = _mm256_slli_epi64(_mm256_add_epi64(ki, _mm256_set1_epi64x(1023)), 52);
    return _mm256_mul_pd(_mm256_fmadd_pd(s, po, pe), _mm256_castsi256_pd(eb));
}

VF_AVX2_AI __m256d vf_erfcx_poly4(__m256d t)
{
    const __m256d t2 = _mm256_mul_pd(t, t), u = _mm256_mul_pd(t2, t2);
    __m256d p0 = _mm256_fmadd_pd(VF_S4(VF_EC20), u, VF_S4(VF_EC16));
    __m256d p1 = _mm256_fmadd_pd(VF_S4(VF_EC17), u, VF_S4(VF_EC13));
    __m256d p2 = _mm256_fmadd_pd(VF_S4(VF_EC18), u, VF_S4(VF_EC14));
    __m256d p3 = _mm256_fmadd_pd(VF_S4(VF_EC19), u, VF_S4(VF_EC15));
    p0 = _mm256_fmadd_pd(p0, u, VF_S4(VF_EC12));
    p1 = _mm256_fmadd_pd(p1, u, VF_S4(VF_EC9));
    p2 = _mm256_fmadd_pd(p2, u, VF_S4(VF_EC10));
    p3 = _mm256_fmadd_pd(p3, u, VF_S4(VF_EC11));
    p0 = _mm256_fmadd_pd(p0, u, VF_S4(VF_EC8));
    p1 = _mm256_fmadd_pd(p1, u, VF_S4(VF_EC5));
    p2 = _mm256_fmadd_pd(p2, u, VF_S4(VF_EC6));
    p3 = _mm256_fmadd_pd(p3, u, VF_S4(VF_EC7));
    p0 = _mm256_fmadd_pd(p0, u, VF_S4(VF_EC4));
    p1 = _mm256_fmadd_pd(p1, u, VF_S4(VF_EC1));
    p2 = _mm256_fmadd_pd(p2, u, VF_S4(VF_EC2));
    p3 = _mm256_fmadd_pd(p3, u, VF_S4(VF_EC3));
    p0 = _mm256_fmadd_pd(p0, u, VF_S4(VF_EC0));
    return _mm256_fmadd_pd(t2, _mm256_fmadd_pd(t, p3, p2), _mm256_fmadd_pd(t, p1, p0));
}

/* r - L round(r / L) on an axis */
VF_AVX2_AI __m256d vf_min_image4(__m256d r, __m256d L, __m256d iL)
{
    return _mm256_fnmadd_pd(L, _mm256_round_pd(_mm256_mul_pd(r, iL), _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC), r);
}

VF_AVX2 static void vf_ewald_real_avx2(const double *y, const double *d, ptrdiff_t ld, const vf_range *rg,
                                       ptrdiff_t nr, double xi, double rc2, const double *mL, const double *iL, int mi,
                                       int sl, int dl, double *o)
{
    const double *y0 = y, *y1 = y + ld, *y2 = y + 2 * ld;
    const double *f0 = d, *f1 = d + ld, *f2 = d + 2 * ld;
    const double *n0 = d + (sl ? 3 : 0) * ld, *n1 = n0 + ld, *n2 = n0 + 2 * ld;
    const double *g0 = n0 + 3 * ld, *g1 = n0 + 4 * ld, *g2 = n0 + 5 * ld;
    const __m256d ML0 = VF_S4(mL[0]), ML1 = VF_S4(mL[1]), ML2 = VF_S4(mL[2]);
    const __m256d IL0 = VF_S4(iL[0]), IL1 = VF_S4(iL[1]), IL2 = VF_S4(iL[2]);
    const __m256d RC2 = VF_S4(rc2), ZERO = _mm256_setzero_pd(), ONE = VF_S4(1.0);
    const __m256d XI = VF_S4(xi), KK = VF_S4(VF_ERFCX_K);
    const __m256d C2 = VF_S4(2.0 * VF_INV_SQPI), CA = VF_S4(4.0 * xi * xi * xi * VF_INV_SQPI);
    const __m256d ISQ = VF_S4(VF_INV_SQPI);
    const double gf0 = 4.0 * xi * VF_INV_SQPI;
    __m256d a0 = ZERO, a1 = ZERO, a2 = ZERO;
    double z0 = 0.0, z1 = 0.0, z2 = 0.0;
    for (ptrdiff_t k = 0; k < nr; ++k) {
    const __m256d X0 = VF_S4(rg[k].x[0]), X1 = VF_S4(rg[k].x[1]), X2 = VF_S4(rg[k].x[2]);
    const ptrdiff_t n = rg[k].s1;
    for (ptrdiff_t s0 = rg[k].s0; s0 < n; s0 += 4) {
        const __m256d valid = _mm256_castsi256_pd(vf_mask4(n - s0));
        __m256d r0 = _mm256_sub_pd(X0, _mm256_loadu_pd(y0 + s0));
        __m256d r1 = _mm256_sub_pd(X1, _mm256_loadu_pd(y1 + s0));
        __m256d r2 = _mm256_sub_pd(X2, _mm256_loadu_pd(y2 + s0));
        if (mi) {
            r0 = vf_min_image4(r0, ML0, IL0);
            r1 = vf_min_image4(r1, ML1, IL1);
            r2 = vf_min_image4(r2, ML2, IL2);
        }
        const __m256d rr = _mm256_fmadd_pd(r2, r2, _mm256_fmadd_pd(r1, r1, _mm256_mul_pd(r0, r0)));
        const __m256d in = _mm256_and_pd(_mm256_and_pd(valid, _mm256_cmp_pd(rr, RC2, _CMP_LT_OQ)),
                                         _mm256_cmp_pd(rr, ZERO, _CMP_GT_OQ));
        if (sl) {
            const int at0 = _mm256_movemask_pd(_mm256_and_pd(valid, _mm256_cmp_pd(rr, ZERO, _CMP_EQ_OQ)));
            if (at0)
                for (int l = 0; l < 4; ++l)
                    if (at0 & (1 << l)) {
                        z0 -= gf0 * f0[s0 + l];
                        z1 -= gf0 * f1[s0 + l];
                        z2 -= gf0 * f2[s0 + l];
                    }
        }
        if (!_mm256_movemask_pd(in))
            continue;
        const __m256d rs = _mm256_blendv_pd(ONE, rr, in);
        const __m256d ri = vf_rsqrt4_or_0(rs);
        const __m256d r = _mm256_mul_pd(rs, ri), yv = _mm256_mul_pd(XI, r);
        const __m256d q1 = _mm256_add_pd(yv, KK), q2 = _mm256_add_pd(yv, ONE);
        const __m256d dd = _mm256_div_pd(ONE, _mm256_mul_pd(q1, q2));       /* 1/((z + K)(1 + z)) */
        const __m256d t = _mm256_mul_pd(_mm256_mul_pd(_mm256_sub_pd(yv, KK), q2), dd);
        const __m256d E = _mm256_mul_pd(_mm256_mul_pd(vf_erfcx_poly4(t), q1), dd);
        const __m256d e = vf_exp4(_mm256_fnmadd_pd(yv, yv, ZERO));
        if (sl) {
            const __m256d F0 = _mm256_loadu_pd(f0 + s0), F1 = _mm256_loadu_pd(f1 + s0), F2 = _mm256_loadu_pd(f2 + s0);
            const __m256d rf = _mm256_fmadd_pd(r2, F2, _mm256_fmadd_pd(r1, F1, _mm256_mul_pd(r0, F0)));
            const __m256d ci = _mm256_and_pd(in, _mm256_mul_pd(_mm256_mul_pd(e, _mm256_fnmadd_pd(C2, yv, E)), ri));
            const __m256d ri3 = _mm256_mul_pd(_mm256_mul_pd(ri, ri), ri);
            const __m256d cr = _mm256_and_pd(in, _mm256_mul_pd(_mm256_mul_pd(_mm256_mul_pd(e, _mm256_fmadd_pd(C2, yv, E)),
                                                                             ri3), rf));
            a0 = _mm256_fmadd_pd(ci, F0, _mm256_fmadd_pd(cr, r0, a0));
            a1 = _mm256_fmadd_pd(ci, F1, _mm256_fmadd_pd(cr, r1, a1));
            a2 = _mm256_fmadd_pd(ci, F2, _mm256_fmadd_pd(cr, r2, a2));
        }
        if (dl) {
            const __m256d N0 = _mm256_loadu_pd(n0 + s0), N1 = _mm256_loadu_pd(n1 + s0), N2 = _mm256_loadu_pd(n2 + s0);
            const __m256d G0 = _mm256_loadu_pd(g0 + s0), G1 = _mm256_loadu_pd(g1 + s0), G2 = _mm256_loadu_pd(g2 + s0);
            const __m256d ri2 = _mm256_mul_pd(ri, ri);
            const __m256d ri5 = _mm256_mul_pd(_mm256_mul_pd(ri2, ri2), ri);
            const __m256d A = _mm256_and_pd(in, _mm256_mul_pd(CA, e));
            /* B = -2 e (3 E + (6 z + 4 z^3) / sqrt(pi)) / r^5 */
            const __m256d poly = _mm256_mul_pd(_mm256_mul_pd(yv, _mm256_fmadd_pd(VF_S4(4.0), _mm256_mul_pd(yv, yv),
                                                                                 VF_S4(6.0))), ISQ);
            const __m256d B = _mm256_and_pd(in, _mm256_mul_pd(_mm256_mul_pd(_mm256_mul_pd(VF_S4(-2.0), e),
                                                                             _mm256_fmadd_pd(VF_S4(3.0), E, poly)), ri5));
            const __m256d rn = _mm256_fmadd_pd(r2, N2, _mm256_fmadd_pd(r1, N1, _mm256_mul_pd(r0, N0)));
            const __m256d rgv = _mm256_fmadd_pd(r2, G2, _mm256_fmadd_pd(r1, G1, _mm256_mul_pd(r0, G0)));
            const __m256d gn = _mm256_fmadd_pd(G2, N2, _mm256_fmadd_pd(G1, N1, _mm256_mul_pd(G0, N0)));
            const __m256d c = _mm256_fmadd_pd(A, gn, _mm256_mul_pd(_mm256_mul_pd(B, rn), rgv));
            a0 = _mm256_fmadd_pd(A, _mm256_fmadd_pd(G0, rn, _mm256_mul_pd(N0, rgv)), _mm256_fmadd_pd(c, r0, a0));
            a1 = _mm256_fmadd_pd(A, _mm256_fmadd_pd(G1, rn, _mm256_mul_pd(N1, rgv)), _mm256_fmadd_pd(c, r1, a1));
            a2 = _mm256_fmadd_pd(A, _mm256_fmadd_pd(G2, rn, _mm256_mul_pd(N2, rgv)), _mm256_fmadd_pd(c, r2, a2));
        }
    }
    }
    const double c = 1.0 / (8.0 * M_PI);
    o[0] += (vf_hsum4(a0) + z0) * c;
    o[1] += (vf_hsum4(a1) + z1) * c;
    o[2] += (vf_hsum4(a2) + z2) * c;
}
#endif

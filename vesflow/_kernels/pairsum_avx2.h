/* The pair sums of pairsum.h on 4 lanes for CPUs with AVX2 and FMA (x86-64-v3, no AVX-512):
 * the arithmetic of its AVX-512 loops, with
 * - 1/r without a square root or a division: the estimate of the exponent bits,
 *   0x5FE6EB50C7B537A9 - (bits(rr) >> 1) (relative error <= 0.035 for every normal rr), refined
 *   by one fourth-order and one third-order step of the series of (1 - e)^(-1/2),
 *   y <- y (1 + e/2 + 3 e^2/8 + 5 e^3/16),  y <- y (1 + e/2 + 3 e^2/8),  e = 1 - rr y^2,
 *   to a relative error of ~1e-16 (the float estimate vrsqrtps needs a range check: rr
 *   outside the floats' range; this one is as fast and needs none);
 * - the (n, 3) arrays de-interleaved 4 rows at a time by 2 blends, 1 lane permute and 3
 *   shuffles per array (a last partial block copied into a zero-padded buffer);
 * - the planar arrays (stokes.planar) read by plain loads, the last partial block masked.
 * Lanes without a source carry zero density and contribute exactly 0.  Several targets share
 * the loaded sources (VF2_MT, VF2_PMT: 16 vector registers hold 2 targets' positions and
 * accumulators).  The values agree with the AVX-512 loops to rounding (4 lanes instead of 8
 * change the summation order). */
#ifndef VESFLOW_PAIRSUM_AVX2_H
#define VESFLOW_PAIRSUM_AVX2_H

#define VF_AVX2 __attribute__((target("avx2,fma")))
#define VF_AVX2_AI VF_AVX2 static inline __attribute__((always_inline))

/* 1/sqrt(rr) for rr > 0, 0 for rr = 0 (lanes of normal rr >= 0) */
VF_AVX2_AI __m256d vf_rsqrt4_or_0(__m256d rr)
{
    const __m256d one = _mm256_set1_pd(1.0), half = _mm256_set1_pd(0.5);
    const __m256d pos = _mm256_cmp_pd(rr, _mm256_setzero_pd(), _CMP_GT_OQ);
    /* the estimate from the exponent bits (relative error <= 0.035), 0 where rr = 0 */
    const __m256i bits = _mm256_sub_epi64(_mm256_set1_epi64x(0x5FE6EB50C7B537A9LL),
                                          _mm256_srli_epi64(_mm256_castpd_si256(rr), 1));
    __m256d y = _mm256_and_pd(pos, _mm256_castsi256_pd(bits));
    /* y (1 + e/2 + 3 e^2/8 + 5 e^3/16), e = 1 - rr y^2: relative error (35/128) e^4 < 6e-6 */
    __m256d e = _mm256_fnmadd_pd(_mm256_mul_pd(rr, y), y, one);
    __m256d p = _mm256_fmadd_pd(_mm256_fmadd_pd(e, _mm256_set1_pd(0.3125), _mm256_set1_pd(0.375)), e, half);
    y = _mm256_fmadd_pd(_mm256_mul_pd(y, e), p, y);
    /* y (1 + e/2 + 3 e^2/8): relative error (5/16) e^3 ~ 1e-16 */
    e = _mm256_fnmadd_pd(_mm256_mul_pd(rr, y), y, one);
    y = _mm256_fmadd_pd(_mm256_mul_pd(y, e), _mm256_fmadd_pd(e, _mm256_set1_pd(0.375), half), y);
    return y;
}

/* rows s .. s + m - 1 (1 <= m <= 4) of an (n, 3) array as three 4-lane columns (0 beyond m) */
VF_AVX2_AI void vf_load3x4(const double *p, ptrdiff_t s, int m, __m256d *c0, __m256d *c1, __m256d *c2)
{
    const double *q = p + 3 * s;
    double buf[12];
    if (m < 4) {
        for (int i = 0; i < 12; ++i)
            buf[i] = i < 3 * m ? q[i] : 0.0;
        q = buf;
    }
    /* v0 = x0 y0 | z0 x1,  v1 = y1 z1 | x2 y2,  v2 = z2 x3 | y3 z3 */
    const __m256d v0 = _mm256_loadu_pd(q), v1 = _mm256_loadu_pd(q + 4), v2 = _mm256_loadu_pd(q + 8);
    const __m256d P = _mm256_blend_pd(v0, v1, 0xC);              /* x0 y0 | x2 y2 */
    const __m256d Q = _mm256_permute2f128_pd(v0, v2, 0x21);      /* z0 x1 | z2 x3 */
    const __m256d R = _mm256_blend_pd(v1, v2, 0xC);              /* y1 z1 | y3 z3 */
    *c0 = _mm256_shuffle_pd(P, Q, 0xA);
    *c1 = _mm256_shuffle_pd(P, R, 0x5);
    *c2 = _mm256_shuffle_pd(Q, R, 0xA);
}

/* planar rows s .. s + 3 of the three runs of m at p (masked beyond m) */
VF_AVX2_AI void vf_load_planar4(const double *p, ptrdiff_t m, ptrdiff_t s, __m256i mask, __m256d *c0, __m256d *c1,
                                __m256d *c2)
{
    *c0 = _mm256_maskload_pd(p + s, mask);
    *c1 = _mm256_maskload_pd(p + m + s, mask);
    *c2 = _mm256_maskload_pd(p + 2 * m + s, mask);
}

/* the mask of the first `left` (>= 1) of 4 lanes */
VF_AVX2_AI __m256i vf_mask4(ptrdiff_t left)
{
    static const int64_t tab[8] = {-1, -1, -1, -1, 0, 0, 0, 0};
    return _mm256_loadu_si256((const __m256i *)(tab + 4 - (left >= 4 ? 4 : left)));
}

VF_AVX2_AI double vf_hsum4(__m256d a)
{
    const __m128d s = _mm_add_pd(_mm256_castpd256_pd128(a), _mm256_extractf128_pd(a, 1));
    return _mm_cvtsd_f64(_mm_add_sd(s, _mm_unpackhi_pd(s, s)));
}

/* 4 sources added to the accumulators a[k] of K targets X[k] (broadcast) */
VF_AVX2_AI void vf_stokeslet_acc4(__m256d (*X)[3], const int K, __m256d y0, __m256d y1, __m256d y2, __m256d f0,
                                  __m256d f1, __m256d f2, __m256d (*a)[3])
{
    for (int k = 0; k < K; ++k) {
        const __m256d r0 = _mm256_sub_pd(X[k][0], y0), r1 = _mm256_sub_pd(X[k][1], y1),
                      r2 = _mm256_sub_pd(X[k][2], y2);
        const __m256d rr = _mm256_fmadd_pd(r2, r2, _mm256_fmadd_pd(r1, r1, _mm256_mul_pd(r0, r0)));
        const __m256d ri = vf_rsqrt4_or_0(rr);
        const __m256d rf = _mm256_mul_pd(_mm256_fmadd_pd(r2, f2, _mm256_fmadd_pd(r1, f1, _mm256_mul_pd(r0, f0))),
                                         _mm256_mul_pd(_mm256_mul_pd(ri, ri), ri));
        a[k][0] = _mm256_fmadd_pd(f0, ri, _mm256_fmadd_pd(r0, rf, a[k][0]));
        a[k][1] = _mm256_fmadd_pd(f1, ri, _mm256_fmadd_pd(r1, rf, a[k][1]));
        a[k][2] = _mm256_fmadd_pd(f2, ri, _mm256_fmadd_pd(r2, rf, a[k][2]));
    }
}

VF_AVX2_AI void vf_stresslet_acc4(__m256d (*X)[3], const int K, __m256d y0, __m256d y1, __m256d y2, __m256d n0,
                                  __m256d n1, __m256d n2, __m256d g0, __m256d g1, __m256d g2, __m256d (*a)[3])
{
    for (int k = 0; k < K; ++k) {
        const __m256d r0 = _mm256_sub_pd(X[k][0], y0), r1 = _mm256_sub_pd(X[k][1], y1),
                      r2 = _mm256_sub_pd(X[k][2], y2);
        const __m256d rr = _mm256_fmadd_pd(r2, r2, _mm256_fmadd_pd(r1, r1, _mm256_mul_pd(r0, r0)));
        const __m256d ri = vf_rsqrt4_or_0(rr);
        const __m256d ri2 = _mm256_mul_pd(ri, ri);
        const __m256d rn = _mm256_fmadd_pd(r2, n2, _mm256_fmadd_pd(r1, n1, _mm256_mul_pd(r0, n0)));
        const __m256d rg = _mm256_fmadd_pd(r2, g2, _mm256_fmadd_pd(r1, g1, _mm256_mul_pd(r0, g0)));
        const __m256d c = _mm256_mul_pd(_mm256_mul_pd(rn, rg), _mm256_mul_pd(_mm256_mul_pd(ri2, ri2), ri));
        a[k][0] = _mm256_fmadd_pd(c, r0, a[k][0]);
        a[k][1] = _mm256_fmadd_pd(c, r1, a[k][1]);
        a[k][2] = _mm256_fmadd_pd(c, r2, a[k][2]);
    }
}

VF_AVX2_AI void vf_init_targets4(const double *x, const int K, __m256d (*X)[3], __m256d (*a)[3])
{
    for (int k = 0; k < K; ++k)
        for (int d = 0; d < 3; ++d) {
            X[k][d] = _mm256_set1_pd(x[3 * k + d]);
            a[k][d] = _mm256_setzero_pd();
        }
}

VF_AVX2_AI void vf_store_targets4(__m256d (*a)[3], const int K, double c, double *o)
{
    for (int k = 0; k < K; ++k)
        for (int d = 0; d < 3; ++d)
            o[3 * k + d] += vf_hsum4(a[k][d]) * c;
}

#define VF2_MT 2
/* K (<= VF2_MT, constant where inlined) targets against the (n, 3) sources s0 .. s1 */
VF_AVX2_AI void vf_stokeslet_range_k4(const double *src, const double *f, ptrdiff_t s0, ptrdiff_t s1,
                                      const double *x, const int K, double *o)
{
    __m256d X[VF2_MT][3], a[VF2_MT][3];
    vf_init_targets4(x, K, X, a);
    for (ptrdiff_t s = s0; s < s1; s += 4) {
        const int m = s1 - s >= 4 ? 4 : (int)(s1 - s);
        __m256d y0, y1, y2, f0, f1, f2;
        vf_load3x4(src, s, m, &y0, &y1, &y2);
        vf_load3x4(f, s, m, &f0, &f1, &f2);
        vf_stokeslet_acc4(X, K, y0, y1, y2, f0, f1, f2, a);
    }
    vf_store_targets4(a, K, 1.0 / (8.0 * M_PI), o);
}

VF_AVX2_AI void vf_stresslet_range_k4(const double *src, const double *nw, const double *g, ptrdiff_t s0,
                                      ptrdiff_t s1, const double *x, const int K, double *o)
{
    __m256d X[VF2_MT][3], a[VF2_MT][3];
    vf_init_targets4(x, K, X, a);
    for (ptrdiff_t s = s0; s < s1; s += 4) {
        const int m = s1 - s >= 4 ? 4 : (int)(s1 - s);
        __m256d y0, y1, y2, n0, n1, n2, g0, g1, g2;
        vf_load3x4(src, s, m, &y0, &y1, &y2);
        vf_load3x4(nw, s, m, &n0, &n1, &n2);
        vf_load3x4(g, s, m, &g0, &g1, &g2);
        vf_stresslet_acc4(X, K, y0, y1, y2, n0, n1, n2, g0, g1, g2, a);
    }
    vf_store_targets4(a, K, -3.0 / (4.0 * M_PI), o);
}

/* K = 1 or 2 targets x[3k..] against the (n, 3) sources s0 .. s1 */
VF_AVX2 static void vf_stokeslet_multi_avx2(const double *src, const double *f, ptrdiff_t s0, ptrdiff_t s1,
                                            const double *x, int K, double *o)
{
    if (K == 2)
        vf_stokeslet_range_k4(src, f, s0, s1, x, 2, o);
    else
        vf_stokeslet_range_k4(src, f, s0, s1, x, 1, o);
}

VF_AVX2 static void vf_stresslet_multi_avx2(const double *src, const double *nw, const double *g, ptrdiff_t s0,
                                            ptrdiff_t s1, const double *x, int K, double *o)
{
    if (K == 2)
        vf_stresslet_range_k4(src, nw, g, s0, s1, x, 2, o);
    else
        vf_stresslet_range_k4(src, nw, g, s0, s1, x, 1, o);
}

/* any K targets, VF2_MT at a time */
VF_AVX2 static void vf_stokeslet_targets_avx2(const double *src, const double *f, ptrdiff_t s0, ptrdiff_t s1,
                                              const double *x, ptrdiff_t K, double *o)
{
    for (ptrdiff_t k = 0; k < K; k += VF2_MT)
        vf_stokeslet_multi_avx2(src, f, s0, s1, x + 3 * k, (int)(K - k < VF2_MT ? K - k : VF2_MT), o + 3 * k);
}

VF_AVX2 static void vf_stresslet_targets_avx2(const double *src, const double *nw, const double *g, ptrdiff_t s0,
                                              ptrdiff_t s1, const double *x, ptrdiff_t K, double *o)
{
    for (ptrdiff_t k = 0; k < K; k += VF2_MT)
        vf_stresslet_multi_avx2(src, nw, g, s0, s1, x + 3 * k, (int)(K - k < VF2_MT ? K - k : VF2_MT), o + 3 * k);
}

/* K (<= VF2_PMT) targets against the m planar sources of one vesicle */
#define VF2_PMT 2
VF_AVX2_AI void vf_stokeslet_planar_k4(const double *src, const double *f, ptrdiff_t m, const double *x, const int K,
                                       double *o)
{
    __m256d X[VF2_PMT][3], a[VF2_PMT][3];
    vf_init_targets4(x, K, X, a);
    for (ptrdiff_t s = 0; s < m; s += 4) {
        const __m256i mask = vf_mask4(m - s);
        __m256d y0, y1, y2, f0, f1, f2;
        vf_load_planar4(src, m, s, mask, &y0, &y1, &y2);
        vf_load_planar4(f, m, s, mask, &f0, &f1, &f2);
        vf_stokeslet_acc4(X, K, y0, y1, y2, f0, f1, f2, a);
    }
    vf_store_targets4(a, K, 1.0 / (8.0 * M_PI), o);
}

VF_AVX2_AI void vf_stresslet_planar_k4(const double *src, const double *nw, const double *g, ptrdiff_t m,
                                       const double *x, const int K, double *o)
{
    __m256d X[VF2_PMT][3], a[VF2_PMT][3];
    vf_init_targets4(x, K, X, a);
    for (ptrdiff_t s = 0; s < m; s += 4) {
        const __m256i mask = vf_mask4(m - s);
        __m256d y0, y1, y2, n0, n1, n2, g0, g1, g2;
        vf_load_planar4(src, m, s, mask, &y0, &y1, &y2);
        vf_load_planar4(nw, m, s, mask, &n0, &n1, &n2);
        vf_load_planar4(g, m, s, mask, &g0, &g1, &g2);
        vf_stresslet_acc4(X, K, y0, y1, y2, n0, n1, n2, g0, g1, g2, a);
    }
    vf_store_targets4(a, K, -3.0 / (4.0 * M_PI), o);
}

/* both layers (vf_both_planar_k's sharing of r and 1/r): o gets S[f], then D[g] */
VF_AVX2_AI void vf_both_planar_k4(const double *src, const double *f, const double *nw, const double *g, ptrdiff_t m,
                                  const double *x, const int K, double *o)
{
    __m256d X[VF2_PMT][3], a[VF2_PMT][3], b[VF2_PMT][3];
    vf_init_targets4(x, K, X, a);
    vf_init_targets4(x, K, X, b);
    for (ptrdiff_t s = 0; s < m; s += 4) {
        const __m256i mask = vf_mask4(m - s);
        __m256d y0, y1, y2, f0, f1, f2, n0, n1, n2, g0, g1, g2;
        vf_load_planar4(src, m, s, mask, &y0, &y1, &y2);
        vf_load_planar4(f, m, s, mask, &f0, &f1, &f2);
        vf_load_planar4(nw, m, s, mask, &n0, &n1, &n2);
        vf_load_planar4(g, m, s, mask, &g0, &g1, &g2);
        for (int k = 0; k < K; ++k) {
            const __m256d r0 = _mm256_sub_pd(X[k][0], y0), r1 = _mm256_sub_pd(X[k][1], y1),
                          r2 = _mm256_sub_pd(X[k][2], y2);
            const __m256d rr = _mm256_fmadd_pd(r2, r2, _mm256_fmadd_pd(r1, r1, _mm256_mul_pd(r0, r0)));
            const __m256d ri = vf_rsqrt4_or_0(rr);
            const __m256d ri2 = _mm256_mul_pd(ri, ri);
            const __m256d rf = _mm256_mul_pd(_mm256_fmadd_pd(r2, f2, _mm256_fmadd_pd(r1, f1, _mm256_mul_pd(r0, f0))),
                                             _mm256_mul_pd(ri2, ri));
            a[k][0] = _mm256_fmadd_pd(f0, ri, _mm256_fmadd_pd(r0, rf, a[k][0]));
            a[k][1] = _mm256_fmadd_pd(f1, ri, _mm256_fmadd_pd(r1, rf, a[k][1]));
            a[k][2] = _mm256_fmadd_pd(f2, ri, _mm256_fmadd_pd(r2, rf, a[k][2]));
            const __m256d rn = _mm256_fmadd_pd(r2, n2, _mm256_fmadd_pd(r1, n1, _mm256_mul_pd(r0, n0)));
            const __m256d rg = _mm256_fmadd_pd(r2, g2, _mm256_fmadd_pd(r1, g1, _mm256_mul_pd(r0, g0)));
            const __m256d c = _mm256_mul_pd(_mm256_mul_pd(rn, rg), _mm256_mul_pd(_mm256_mul_pd(ri2, ri2), ri));
            b[k][0] = _mm256_fmadd_pd(c, r0, b[k][0]);
            b[k][1] = _mm256_fmadd_pd(c, r1, b[k][1]);
            b[k][2] = _mm256_fmadd_pd(c, r2, b[k][2]);
        }
    }
    vf_store_targets4(a, K, 1.0 / (8.0 * M_PI), o);
    vf_store_targets4(b, K, -3.0 / (4.0 * M_PI), o);
}

VF_AVX2 static void vf_stokeslet_planar_avx2(const double *src, const double *f, ptrdiff_t m, const double *x,
                                             ptrdiff_t K, double *o)
{
    ptrdiff_t k = 0;
    for (; K - k >= 2; k += 2)
        vf_stokeslet_planar_k4(src, f, m, x + 3 * k, 2, o + 3 * k);
    if (K - k == 1)
        vf_stokeslet_planar_k4(src, f, m, x + 3 * k, 1, o + 3 * k);
}

VF_AVX2 static void vf_stresslet_planar_avx2(const double *src, const double *nw, const double *g, ptrdiff_t m,
                                             const double *x, ptrdiff_t K, double *o)
{
    ptrdiff_t k = 0;
    for (; K - k >= 2; k += 2)
        vf_stresslet_planar_k4(src, nw, g, m, x + 3 * k, 2, o + 3 * k);
    if (K - k == 1)
        vf_stresslet_planar_k4(src, nw, g, m, x + 3 * k, 1, o + 3 * k);
}

VF_AVX2 static void vf_both_planar_avx2(const double *src, const double *f, const double *nw, const double *g,
                                        ptrdiff_t m, const double *x, ptrdiff_t K, double *o)
{
    ptrdiff_t k = 0;
    for (; K - k >= 2; k += 2)
        vf_both_planar_k4(src, f, nw, g, m, x + 3 * k, 2, o + 3 * k);
    if (K - k == 1)
        vf_both_planar_k4(src, f, nw, g, m, x + 3 * k, 1, o + 3 * k);
}
#endif

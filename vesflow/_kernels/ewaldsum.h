/* The real-space sums of the spectral Ewald method (ewald.pyx), written for the vectorizer as
 * pairsum.h: one target against ranges of sources in place (structure of arrays), the
 * pairs outside the cutoff and the coincident ones masked by selects, not branches.
 *
 * With z = xi r, e = exp(-z^2) and E = erfcx(z) = exp(z^2) erfc(z) (so erfc(z) = e E):
 *   G^R f = a1 / r f + a2 / r^3 r (r . f),     a1 = e (E - 2 z / sqrt(pi)), a2 = e (E + 2 z / sqrt(pi))
 *   T^R:(g nw) = A ((r.nw) g + (r.g) nw + (g.nw) r) + B (r.nw)(r.g) r,
 *              A = 4 xi^3 e / sqrt(pi),  B = -2 e (3 E + (6 z + 4 z^3) / sqrt(pi)) / r^5
 * (ewald.pyx's module docstring).  Both functions are computed here without libm:
 * - exp(x), -700 <= x <= 0: x = n ln 2 + s (Cody-Waite, |s| <= ln 2 / 2), exp(s) by its Taylor
 *   polynomial of degree 12 (remainder < 2e-16; its even and odd parts as two short chains),
 *   2^n from the exponent bits; the erfcx polynomial split likewise into four (Estrin);
 * - erfcx(z), z >= 0: (1 + z) erfcx(z) is a smooth function of t = (z - K)/(z + K) on [-1, 1]
 *   (Weideman 1994's variable), interpolated at 21 Chebyshev points (K = 3.5; relative error
 *   of erfcx below 6e-15 for every z >= 0, measured against scipy.special.erfcx; the
 *   coefficients below are its monomial form, tests/layerpot/test_ewald.py checks the result).
 * One square root and one division per pair.  Results agree with libm's erfc/exp to ~1e-14
 * relative; the summation order differs from a scalar loop (vector lanes, FMA). */
#ifndef VESFLOW_EWALDSUM_H
#define VESFLOW_EWALDSUM_H
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#include "pairsum.h"

#define VF_AI static inline __attribute__((always_inline))
#define VF_ERFCX_K 3.5
#define VF_INV_SQPI 0.56418958354775628695   /* 1/sqrt(pi) */

/* exp(x) for -700 <= x <= 0 (smaller x are clamped to -700) */
VF_AI double vf_exp_nonpos(double x)
{
    x = x > -700.0 ? x : -700.0;
    const double shift = 6755399441055744.0;            /* 1.5 2^52: kd's low bits hold n */
    double kd = x * 1.4426950408889634074 + shift;
    int64_t ki;
    memcpy(&ki, &kd, sizeof ki);
    kd -= shift;
    double s = x - kd * 6.93147180369123816490e-01;      /* ln 2 high part (exact product) */
    s = s - kd * 1.90821492927058770002e-10;             /* ln 2 low part */
    /* exp(s) = E(s^2) + s O(s^2) (two short chains instead of 12 dependent steps) */
    const double s2 = s * s;
    double pe = 2.08767569878680989792e-09;              /* 1/12! */
    pe = pe * s2 + 2.75573192239858906526e-07;           /* 1/10! */
    pe = pe * s2 + 2.48015873015873015873e-05;           /* 1/8! */
    pe = pe * s2 + 1.38888888888888888889e-03;           /* 1/6! */
    pe = pe * s2 + 4.16666666666666666667e-02;           /* 1/4! */
    pe = pe * s2 + 0.5;
    pe = pe * s2 + 1.0;
    double po = 2.50521083854417187751e-08;              /* 1/11! */
    po = po * s2 + 2.75573192239858906526e-06;           /* 1/9! */
    po = po * s2 + 1.98412698412698412698e-04;           /* 1/7! */
    po = po * s2 + 8.33333333333333333333e-03;           /* 1/5! */
    po = po * s2 + 1.66666666666666666667e-01;           /* 1/3! */
    po = po * s2 + 1.0;
    const double p = pe + s * po;
    int64_t eb = (ki - (int64_t)0x4338000000000000LL + 1023) << 52;
    double sc;
    memcpy(&sc, &eb, sizeof sc);
    return p * sc;
}

/* (1 + z) erfcx(z) as a polynomial in t = (z - K)/(z + K): coefficients VF_EC<k> of t^k,
 * evaluated as P0(t^4) + t P1(t^4) + t^2 (P2(t^4) + t P3(t^4)) (Estrin's split: four short
 * Horner chains instead of one of 20 dependent multiply-adds) */
#define VF_EC0 6.98821450240024400e-01
#define VF_EC1 -2.14637112485262460e-01
#define VF_EC2 1.11287442633976441e-01
#define VF_EC3 -3.19097148006058304e-02
#define VF_EC4 -1.03308956245707559e-02
#define VF_EC5 2.12731962116369695e-02
#define VF_EC6 -1.59232824563491603e-02
#define VF_EC7 7.42854725937949680e-03
#define VF_EC8 -1.97381737697253706e-03
#define VF_EC9 -6.86235935480495265e-06
#define VF_EC10 2.28149766349759097e-04
#define VF_EC11 -6.30728965800816433e-05
#define VF_EC12 -1.47181519522821816e-05
#define VF_EC13 1.12735891245147664e-05
#define VF_EC14 4.05243606323810795e-07
#define VF_EC15 -1.66476372306377834e-06
#define VF_EC16 7.25760403346465183e-08
#define VF_EC17 2.21318209186002785e-07
#define VF_EC18 -1.66417145283581546e-08
#define VF_EC19 -1.92989490664923047e-08
#define VF_EC20 1.56543981576414162e-09
VF_AI double vf_erfcx_poly(double t)
{
    const double t2 = t * t, u = t2 * t2;
    const double p0 = (((((VF_EC20 * u + VF_EC16) * u + VF_EC12) * u + VF_EC8) * u + VF_EC4) * u + VF_EC0);
    const double p1 = ((((VF_EC17 * u + VF_EC13) * u + VF_EC9) * u + VF_EC5) * u + VF_EC1);
    const double p2 = ((((VF_EC18 * u + VF_EC14) * u + VF_EC10) * u + VF_EC6) * u + VF_EC2);
    const double p3 = ((((VF_EC19 * u + VF_EC15) * u + VF_EC11) * u + VF_EC7) * u + VF_EC3);
    return (p0 + t * p1) + t2 * (p2 + t * p3);
}

/* r = sqrt(rr) > 0: *ri = 1/r, *e = exp(-z^2), *E = erfcx(z), z = xi r (one division) */
VF_AI void vf_real_parts(double rr, double xi, double *ri, double *z, double *e, double *E)
{
    const double r = sqrt(rr), y = xi * r;
    const double q1 = y + VF_ERFCX_K, q2 = 1.0 + y;
    const double d = 1.0 / (r * q1 * q2);
    *ri = q1 * q2 * d;
    const double t = (y - VF_ERFCX_K) * q2 * r * d;
    *E = vf_erfcx_poly(t) * q1 * r * d;
    *e = vf_exp_nonpos(-y * y);
    *z = y;
}

/* round to the nearest integer (|v| < 2^51) */
VF_AI double vf_round(double v)
{
    const double shift = 6755399441055744.0;
    return (v + shift) - shift;
}

/* The sources in place: structure-of-arrays columns of leading dimension ld (>= the last
 * range's end + VF_BLOCK - 1: a block may read up to 7 rows past a range's end, masked, never
 * summed): positions y (3 columns, cell order) and the densities d: f (3, single layer), then
 * nw and g (3 + 3, double layer).  A target is summed over a list of ranges of rows, each with
 * the target's position minus the periodic image shift of the range's cells:
 * o[0:3] += (1/(8 pi)) sum_ranges sum_{s0 <= s < s1} [inside rc: G^R(r) f_s + T^R(r):(g_s nw_s);
 * r = 0: -G^F(0) f_s],  r = (x - shift) - y_s (minimum image on the axes with mL[a] = L_a != 0,
 * iL[a] = 1/L_a).  A range goes in blocks of VF_BLOCK (one AVX-512 vector) from its start: a
 * block with no source inside rc is skipped after its distances (neighbouring sources lie close
 * together: a cell keeps each vesicle's sources in surface order). */
#define VF_BLOCK 8

typedef struct {
    ptrdiff_t s0, s1;        /* rows s0 .. s1 - 1 */
    double x[3];             /* the target minus the image shift of these rows' cells */
} vf_range;

VF_AI void vf_ewald_real_generic(const double *y, const double *d, ptrdiff_t ld, const vf_range *rg, ptrdiff_t nr,
                                 double xi, double rc2, const double *mL, const double *iL, const int mi, const int sl,
                                 const int dl, double *o)
{
    const double *y0 = y, *y1 = y + ld, *y2 = y + 2 * ld;
    const double *f0 = d, *f1 = d + ld, *f2 = d + 2 * ld;
    const double *n0 = d + (sl ? 3 : 0) * ld, *n1 = n0 + ld, *n2 = n0 + 2 * ld;
    const double *g0 = n0 + 3 * ld, *g1 = n0 + 4 * ld, *g2 = n0 + 5 * ld;
    const double mL0 = mL[0], mL1 = mL[1], mL2 = mL[2], iL0 = iL[0], iL1 = iL[1], iL2 = iL[2];
    const double c2 = 2.0 * VF_INV_SQPI, gf0 = 4.0 * xi * VF_INV_SQPI, ca = 4.0 * xi * xi * xi * VF_INV_SQPI;
    double a0[VF_BLOCK], a1[VF_BLOCK], a2[VF_BLOCK];
    for (int l = 0; l < VF_BLOCK; ++l) {
        a0[l] = 0.0;
        a1[l] = 0.0;
        a2[l] = 0.0;
    }
    for (ptrdiff_t k = 0; k < nr; ++k) {
    const double x0 = rg[k].x[0], x1 = rg[k].x[1], x2 = rg[k].x[2];
    const ptrdiff_t n = rg[k].s1;
    for (ptrdiff_t s0 = rg[k].s0; s0 < n; s0 += VF_BLOCK) {
        int any = 0;
#pragma omp simd reduction(| : any)
        for (int l = 0; l < VF_BLOCK; ++l) {
            const ptrdiff_t s = s0 + l;
            double r0 = x0 - y0[s], r1 = x1 - y1[s], r2 = x2 - y2[s];
            if (mi) {
                r0 -= mL0 * vf_round(r0 * iL0);
                r1 -= mL1 * vf_round(r1 * iL1);
                r2 -= mL2 * vf_round(r2 * iL2);
            }
            any |= (s < n) & (r0 * r0 + r1 * r1 + r2 * r2 < rc2);
        }
        if (!any)
            continue;
#pragma omp simd
        for (int l = 0; l < VF_BLOCK; ++l) {
            const ptrdiff_t s = s0 + l;
            double r0 = x0 - y0[s], r1 = x1 - y1[s], r2 = x2 - y2[s];
            if (mi) {
                r0 -= mL0 * vf_round(r0 * iL0);
                r1 -= mL1 * vf_round(r1 * iL1);
                r2 -= mL2 * vf_round(r2 * iL2);
            }
            const double rr = r0 * r0 + r1 * r1 + r2 * r2;
            const int valid = s < n;
            const int inside = valid & (rr < rc2) & (rr > 0.0);
            double ri, z, e, E;
            vf_real_parts(inside ? rr : 1.0, xi, &ri, &z, &e, &E);
            if (sl) {
                const double rf = r0 * f0[s] + r1 * f1[s] + r2 * f2[s];
                const double ci = inside ? e * (E - c2 * z) * ri : (valid & (rr == 0.0) ? -gf0 : 0.0);
                const double cr = inside ? e * (E + c2 * z) * (ri * ri * ri) * rf : 0.0;
                a0[l] += ci * f0[s] + cr * r0;
                a1[l] += ci * f1[s] + cr * r1;
                a2[l] += ci * f2[s] + cr * r2;
            }
            if (dl) {
                const double ri2 = ri * ri;
                const double A = inside ? ca * e : 0.0;
                const double B = inside ? -2.0 * e * (3.0 * E + (6.0 * z + 4.0 * z * z * z) * VF_INV_SQPI)
                                              * (ri2 * ri2 * ri)
                                        : 0.0;
                const double rn = r0 * n0[s] + r1 * n1[s] + r2 * n2[s];
                const double rg_ = r0 * g0[s] + r1 * g1[s] + r2 * g2[s];
                const double gn = g0[s] * n0[s] + g1[s] * n1[s] + g2[s] * n2[s];
                const double c = A * gn + B * rn * rg_;
                a0[l] += A * (g0[s] * rn + n0[s] * rg_) + c * r0;
                a1[l] += A * (g1[s] * rn + n1[s] * rg_) + c * r1;
                a2[l] += A * (g2[s] * rn + n2[s] * rg_) + c * r2;
            }
        }
    }
    }
    double t0 = 0.0, t1 = 0.0, t2 = 0.0;
    for (int l = 0; l < VF_BLOCK; ++l) {
        t0 += a0[l];
        t1 += a1[l];
        t2 += a2[l];
    }
    const double c = 1.0 / (8.0 * M_PI);
    o[0] += t0 * c;
    o[1] += t1 * c;
    o[2] += t2 * c;
}

#define VF_REAL_VARIANT(name, MI, SL, DL)                                                                  \
    VF_CLONES static void name(const double *y, const double *d, ptrdiff_t ld, const vf_range *rg,          \
                               ptrdiff_t nr, double xi, double rc2, const double *mL, const double *iL,       \
                               double *o)                                                                     \
    {                                                                                                      \
        vf_ewald_real_generic(y, d, ld, rg, nr, xi, rc2, mL, iL, MI, SL, DL, o);                           \
    }
VF_REAL_VARIANT(vf_ewald_real_s, 0, 1, 0)
VF_REAL_VARIANT(vf_ewald_real_d, 0, 0, 1)
VF_REAL_VARIANT(vf_ewald_real_sd, 0, 1, 1)
VF_REAL_VARIANT(vf_ewald_real_s_mi, 1, 1, 0)
VF_REAL_VARIANT(vf_ewald_real_d_mi, 1, 0, 1)
VF_REAL_VARIANT(vf_ewald_real_sd_mi, 1, 1, 1)

#ifdef VF_X86_PATHS
#define VF_AVX512 __attribute__((target("avx512f,avx512dq,fma")))
#define VF_S(c) _mm512_set1_pd(c)

/* exp(x), -700 <= x <= 0, 8 lanes (vf_exp_nonpos's reduction and polynomial; n by roundscale,
 * 2^n applied by scalef: 2 operations fewer than the shift and exponent-bit tricks) */
VF_AVX512 static inline __m512d vf_exp8(__m512d x)
{
    x = _mm512_max_pd(x, _mm512_set1_pd(-700.0));
    const __m512d kd = _mm512_roundscale_pd(_mm512_mul_pd(x, _mm512_set1_pd(1.4426950408889634074)),
                                            _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    __m512d s = _mm512_fnmadd_pd(kd, _mm512_set1_pd(6.93147180369123816490e-01), x);
    s = _mm512_fnmadd_pd(kd, _mm512_set1_pd(1.90821492927058770002e-10), s);
    const __m512d s2 = _mm512_mul_pd(s, s);
    __m512d pe = _mm512_fmadd_pd(VF_S(2.08767569878680989792e-09), s2, VF_S(2.75573192239858906526e-07));
    __m512d po = _mm512_fmadd_pd(VF_S(2.50521083854417187751e-08), s2, VF_S(2.75573192239858906526e-06));
    pe = _mm512_fmadd_pd(pe, s2, VF_S(2.48015873015873015873e-05));
    po = _mm512_fmadd_pd(po, s2, VF_S(1.98412698412698412698e-04));
    pe = _mm512_fmadd_pd(pe, s2, VF_S(1.38888888888888888889e-03));
    po = _mm512_fmadd_pd(po, s2, VF_S(8.33333333333333333333e-03));
    pe = _mm512_fmadd_pd(pe, s2, VF_S(4.16666666666666666667e-02));
    po = _mm512_fmadd_pd(po, s2, VF_S(1.66666666666666666667e-01));
    pe = _mm512_fmadd_pd(pe, s2, VF_S(0.5));
    po = _mm512_fmadd_pd(po, s2, VF_S(1.0));
    pe = _mm512_fmadd_pd(pe, s2, VF_S(1.0));
    return _mm512_scalef_pd(_mm512_fmadd_pd(s, po, pe), kd);
}

/* (1 + z) erfcx(z) as the polynomial in t of vf_erfcx_poly (the same split), 8 lanes */
VF_AVX512 static inline __m512d vf_erfcx_poly8(__m512d t)
{
    const __m512d t2 = _mm512_mul_pd(t, t), u = _mm512_mul_pd(t2, t2);
    __m512d p0 = _mm512_fmadd_pd(VF_S(VF_EC20), u, VF_S(VF_EC16));
    __m512d p1 = _mm512_fmadd_pd(VF_S(VF_EC17), u, VF_S(VF_EC13));
    __m512d p2 = _mm512_fmadd_pd(VF_S(VF_EC18), u, VF_S(VF_EC14));
    __m512d p3 = _mm512_fmadd_pd(VF_S(VF_EC19), u, VF_S(VF_EC15));
    p0 = _mm512_fmadd_pd(p0, u, VF_S(VF_EC12));
    p1 = _mm512_fmadd_pd(p1, u, VF_S(VF_EC9));
    p2 = _mm512_fmadd_pd(p2, u, VF_S(VF_EC10));
    p3 = _mm512_fmadd_pd(p3, u, VF_S(VF_EC11));
    p0 = _mm512_fmadd_pd(p0, u, VF_S(VF_EC8));
    p1 = _mm512_fmadd_pd(p1, u, VF_S(VF_EC5));
    p2 = _mm512_fmadd_pd(p2, u, VF_S(VF_EC6));
    p3 = _mm512_fmadd_pd(p3, u, VF_S(VF_EC7));
    p0 = _mm512_fmadd_pd(p0, u, VF_S(VF_EC4));
    p1 = _mm512_fmadd_pd(p1, u, VF_S(VF_EC1));
    p2 = _mm512_fmadd_pd(p2, u, VF_S(VF_EC2));
    p3 = _mm512_fmadd_pd(p3, u, VF_S(VF_EC3));
    p0 = _mm512_fmadd_pd(p0, u, VF_S(VF_EC0));
    return _mm512_fmadd_pd(t2, _mm512_fmadd_pd(t, p3, p2), _mm512_fmadd_pd(t, p1, p0));
}

/* 1/sqrt(a) and 1/a, a > 0: the 14-bit estimates of AVX-512F refined by two Newton steps
 * (relative error ~1e-16, no division unit) */
VF_AVX512 static inline __m512d vf_rsqrt8(__m512d a)
{
    __m512d y = _mm512_rsqrt14_pd(a);
    const __m512d h = _mm512_mul_pd(a, _mm512_set1_pd(0.5)), c = _mm512_set1_pd(1.5);
    y = _mm512_mul_pd(y, _mm512_fnmadd_pd(_mm512_mul_pd(h, y), y, c));
    y = _mm512_mul_pd(y, _mm512_fnmadd_pd(_mm512_mul_pd(h, y), y, c));
    return y;
}

VF_AVX512 static inline __m512d vf_rcp8(__m512d a)
{
    __m512d y = _mm512_rcp14_pd(a);
    const __m512d one = _mm512_set1_pd(1.0);
    y = _mm512_fmadd_pd(y, _mm512_fnmadd_pd(a, y, one), y);
    y = _mm512_fmadd_pd(y, _mm512_fnmadd_pd(a, y, one), y);
    return y;
}

/* vf_ewald_real_generic with AVX-512 intrinsics: blocks of 8 sources of each range, a block without a
 * source inside rc skipped, coincident pairs (rare) added lane by lane */
VF_AVX512 static void vf_ewald_real_avx512(const double *y, const double *d, ptrdiff_t ld, const vf_range *rg,
                                           ptrdiff_t nr, double xi, double rc2, const double *mL, const double *iL,
                                           int mi, int sl, int dl, double *o)
{
    const double *y0 = y, *y1 = y + ld, *y2 = y + 2 * ld;
    const double *f0 = d, *f1 = d + ld, *f2 = d + 2 * ld;
    const double *n0 = d + (sl ? 3 : 0) * ld, *n1 = n0 + ld, *n2 = n0 + 2 * ld;
    const double *g0 = n0 + 3 * ld, *g1 = n0 + 4 * ld, *g2 = n0 + 5 * ld;
    const __m512d ML0 = _mm512_set1_pd(mL[0]), ML1 = _mm512_set1_pd(mL[1]), ML2 = _mm512_set1_pd(mL[2]);
    const __m512d IL0 = _mm512_set1_pd(iL[0]), IL1 = _mm512_set1_pd(iL[1]), IL2 = _mm512_set1_pd(iL[2]);
    const __m512d RC2 = _mm512_set1_pd(rc2), ZERO = _mm512_setzero_pd(), ONE = _mm512_set1_pd(1.0);
    const __m512d XI = _mm512_set1_pd(xi), KK = _mm512_set1_pd(VF_ERFCX_K);
    const __m512d C2 = _mm512_set1_pd(2.0 * VF_INV_SQPI), CA = _mm512_set1_pd(4.0 * xi * xi * xi * VF_INV_SQPI);
    const __m512d ISQ = _mm512_set1_pd(VF_INV_SQPI);
    const double gf0 = 4.0 * xi * VF_INV_SQPI;
    __m512d a0 = ZERO, a1 = ZERO, a2 = ZERO;
    double z0 = 0.0, z1 = 0.0, z2 = 0.0;
    for (ptrdiff_t k = 0; k < nr; ++k) {
    const __m512d X0 = _mm512_set1_pd(rg[k].x[0]), X1 = _mm512_set1_pd(rg[k].x[1]), X2 = _mm512_set1_pd(rg[k].x[2]);
    const ptrdiff_t n = rg[k].s1;
    for (ptrdiff_t s0 = rg[k].s0; s0 < n; s0 += 8) {
        const __mmask8 valid = n - s0 >= 8 ? (__mmask8)0xFF : (__mmask8)((1u << (n - s0)) - 1u);
        __m512d r0 = _mm512_sub_pd(X0, _mm512_loadu_pd(y0 + s0));
        __m512d r1 = _mm512_sub_pd(X1, _mm512_loadu_pd(y1 + s0));
        __m512d r2 = _mm512_sub_pd(X2, _mm512_loadu_pd(y2 + s0));
        if (mi) {
            r0 = _mm512_fnmadd_pd(ML0, _mm512_roundscale_pd(_mm512_mul_pd(r0, IL0), _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC), r0);
            r1 = _mm512_fnmadd_pd(ML1, _mm512_roundscale_pd(_mm512_mul_pd(r1, IL1), _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC), r1);
            r2 = _mm512_fnmadd_pd(ML2, _mm512_roundscale_pd(_mm512_mul_pd(r2, IL2), _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC), r2);
        }
        const __m512d rr = _mm512_fmadd_pd(r2, r2, _mm512_fmadd_pd(r1, r1, _mm512_mul_pd(r0, r0)));
        const __mmask8 in = _mm512_mask_cmp_pd_mask(valid, rr, RC2, _CMP_LT_OQ)
                          & _mm512_cmp_pd_mask(rr, ZERO, _CMP_GT_OQ);
        const __mmask8 at0 = _mm512_mask_cmp_pd_mask(valid, rr, ZERO, _CMP_EQ_OQ);
        if (sl && at0) {
            for (int l = 0; l < 8; ++l)
                if (at0 & (1u << l)) {
                    z0 -= gf0 * f0[s0 + l];
                    z1 -= gf0 * f1[s0 + l];
                    z2 -= gf0 * f2[s0 + l];
                }
        }
        if (!in)
            continue;
        const __m512d rs = _mm512_mask_blend_pd(in, ONE, rr);
        const __m512d ri = vf_rsqrt8(rs);
        const __m512d r = _mm512_mul_pd(rs, ri), y = _mm512_mul_pd(XI, r);
        const __m512d q1 = _mm512_add_pd(y, KK), q2 = _mm512_add_pd(y, ONE);
        const __m512d d = vf_rcp8(_mm512_mul_pd(q1, q2));                  /* 1/((z + K)(1 + z)) */
        const __m512d t = _mm512_mul_pd(_mm512_mul_pd(_mm512_sub_pd(y, KK), q2), d);
        const __m512d E = _mm512_mul_pd(_mm512_mul_pd(vf_erfcx_poly8(t), q1), d);
        const __m512d e = vf_exp8(_mm512_fnmadd_pd(y, y, ZERO));
        if (sl) {
            const __m512d F0 = _mm512_loadu_pd(f0 + s0), F1 = _mm512_loadu_pd(f1 + s0), F2 = _mm512_loadu_pd(f2 + s0);
            const __m512d rf = _mm512_fmadd_pd(r2, F2, _mm512_fmadd_pd(r1, F1, _mm512_mul_pd(r0, F0)));
            const __m512d ci = _mm512_maskz_mul_pd(in, _mm512_mul_pd(e, _mm512_fnmadd_pd(C2, y, E)), ri);
            const __m512d ri3 = _mm512_mul_pd(_mm512_mul_pd(ri, ri), ri);
            const __m512d cr = _mm512_maskz_mul_pd(in, _mm512_mul_pd(_mm512_mul_pd(e, _mm512_fmadd_pd(C2, y, E)), ri3), rf);
            a0 = _mm512_fmadd_pd(ci, F0, _mm512_fmadd_pd(cr, r0, a0));
            a1 = _mm512_fmadd_pd(ci, F1, _mm512_fmadd_pd(cr, r1, a1));
            a2 = _mm512_fmadd_pd(ci, F2, _mm512_fmadd_pd(cr, r2, a2));
        }
        if (dl) {
            const __m512d N0 = _mm512_loadu_pd(n0 + s0), N1 = _mm512_loadu_pd(n1 + s0), N2 = _mm512_loadu_pd(n2 + s0);
            const __m512d G0 = _mm512_loadu_pd(g0 + s0), G1 = _mm512_loadu_pd(g1 + s0), G2 = _mm512_loadu_pd(g2 + s0);
            const __m512d ri2 = _mm512_mul_pd(ri, ri);
            const __m512d ri5 = _mm512_mul_pd(_mm512_mul_pd(ri2, ri2), ri);
            const __m512d A = _mm512_maskz_mul_pd(in, CA, e);
            /* B = -2 e (3 E + (6 z + 4 z^3) / sqrt(pi)) / r^5 */
            const __m512d poly = _mm512_mul_pd(_mm512_mul_pd(y, _mm512_fmadd_pd(_mm512_set1_pd(4.0), _mm512_mul_pd(y, y),
                                                                                _mm512_set1_pd(6.0))), ISQ);
            const __m512d B = _mm512_maskz_mul_pd(in, _mm512_mul_pd(_mm512_mul_pd(_mm512_set1_pd(-2.0), e),
                                                                     _mm512_fmadd_pd(_mm512_set1_pd(3.0), E, poly)), ri5);
            const __m512d rn = _mm512_fmadd_pd(r2, N2, _mm512_fmadd_pd(r1, N1, _mm512_mul_pd(r0, N0)));
            const __m512d rgv = _mm512_fmadd_pd(r2, G2, _mm512_fmadd_pd(r1, G1, _mm512_mul_pd(r0, G0)));
            const __m512d gn = _mm512_fmadd_pd(G2, N2, _mm512_fmadd_pd(G1, N1, _mm512_mul_pd(G0, N0)));
            const __m512d c = _mm512_fmadd_pd(A, gn, _mm512_mul_pd(_mm512_mul_pd(B, rn), rgv));
            a0 = _mm512_fmadd_pd(A, _mm512_fmadd_pd(G0, rn, _mm512_mul_pd(N0, rgv)), _mm512_fmadd_pd(c, r0, a0));
            a1 = _mm512_fmadd_pd(A, _mm512_fmadd_pd(G1, rn, _mm512_mul_pd(N1, rgv)), _mm512_fmadd_pd(c, r1, a1));
            a2 = _mm512_fmadd_pd(A, _mm512_fmadd_pd(G2, rn, _mm512_mul_pd(N2, rgv)), _mm512_fmadd_pd(c, r2, a2));
        }
    }
    }
    const double c = 1.0 / (8.0 * M_PI);
    o[0] += (_mm512_reduce_add_pd(a0) + z0) * c;
    o[1] += (_mm512_reduce_add_pd(a1) + z1) * c;
    o[2] += (_mm512_reduce_add_pd(a2) + z2) * c;
}

#endif

#ifdef VF_X86_PATHS
#include "ewaldsum_avx2.h"
#endif

/* the real-space sum of one target over nr ranges of sources in place (layout above); sl, dl:
 * layers present; mi: minimum image on the axes with mL != 0 */
static void vf_ewald_real(const double *y, const double *d, ptrdiff_t ld, const vf_range *rg, ptrdiff_t nr,
                          double xi, double rc2, const double *mL, const double *iL, int mi, int sl, int dl, double *o)
{
#ifdef VF_X86_PATHS
    switch (vf_pairsum_use()) {       /* the path of pairsum.h's sums */
    case VF_PATH_AVX512: vf_ewald_real_avx512(y, d, ld, rg, nr, xi, rc2, mL, iL, mi, sl, dl, o); return;
    case VF_PATH_AVX2: vf_ewald_real_avx2(y, d, ld, rg, nr, xi, rc2, mL, iL, mi, sl, dl, o); return;
    default: break;
    }
#endif
    if (mi) {
        if (sl && dl) vf_ewald_real_sd_mi(y, d, ld, rg, nr, xi, rc2, mL, iL, o);
        else if (sl) vf_ewald_real_s_mi(y, d, ld, rg, nr, xi, rc2, mL, iL, o);
        else vf_ewald_real_d_mi(y, d, ld, rg, nr, xi, rc2, mL, iL, o);
    } else {
        if (sl && dl) vf_ewald_real_sd(y, d, ld, rg, nr, xi, rc2, mL, iL, o);
        else if (sl) vf_ewald_real_s(y, d, ld, rg, nr, xi, rc2, mL, iL, o);
        else vf_ewald_real_d(y, d, ld, rg, nr, xi, rc2, mL, iL, o);
    }
}

/* The smooth (Fourier) parts of the kernels of one target x against S sources (ewald.pyx's
 * smooth_kernel_tables: G^F = ci I + ca r r^T, T^F:(. nw) with A and b; structure of arrays
 * y0..2, weights w, nw0..2), the 6 components ab (00, 01, 02, 11, 12, 22) of each into
 * sg[ab * S + s] and db[ab * S + s] (times w / (8 pi), resp. 1 / (8 pi)).  z = xi r >= 1/2 from
 * erf = 1 - exp(-z^2) erfcx(z) (vf_real_parts, no libm); below, the Taylor series in z^2 of
 * ewald.pyx (14 terms: remainder < 1e-17 relative), so that r = 0 is finite. */
#define VF_SMOOTH_Z2 0.25
#define VF_SMOOTH_TERMS 14
VF_AI void vf_smooth_row_generic(const double *x, const double *y0, const double *y1, const double *y2,
                                 const double *w, const double *n0, const double *n1, const double *n2, ptrdiff_t S,
                                 double xi, const int want_s, const int want_d, double *sg, double *db)
{
    const double xi2 = xi * xi, xi3 = xi2 * xi, c8 = 1.0 / (8.0 * M_PI);
    const double c2 = 2.0 * xi * VF_INV_SQPI;
    /* series coefficients in z^2: erf(z)/r, ca and b (ewald.pyx's _gf_coef, _tf_coef) */
    double ce[VF_SMOOTH_TERMS], cg[VF_SMOOTH_TERMS], cb[VF_SMOOTH_TERMS];
    double fact = 1.0;                                    /* n! */
    for (int n = 0; n < VF_SMOOTH_TERMS; ++n) {
        const double sgn = (n % 2) ? -1.0 : 1.0;
        if (n > 0)
            fact *= n;
        ce[n] = c2 * sgn / (fact * (2 * n + 1));                                    /* z^(2n) */
        /* ca: (2 xi^3/sqrt(pi)) (-1)^(m+1) 2m/(2m+1) z^(2m-2)/m!, m = n + 1 */
        cg[n] = 2.0 * xi3 * VF_INV_SQPI * sgn * (2.0 * (n + 1)) / ((2.0 * n + 3.0) * fact * (n + 1));
        /* b: -(16 xi^5/sqrt(pi)) (-1)^m m(m-1)/((2m+1) m!) z^(2m-4), m = n + 2 */
        cb[n] = -16.0 * xi3 * xi2 * VF_INV_SQPI * sgn * ((n + 2.0) * (n + 1.0)) / ((2.0 * n + 5.0) * fact * (n + 1.0) * (n + 2.0));
    }
    const double x0 = x[0], x1 = x[1], x2 = x[2];
#pragma omp simd
    for (ptrdiff_t s = 0; s < S; ++s) {
        const double r0 = x0 - y0[s], r1 = x1 - y1[s], r2 = x2 - y2[s];
        const double rr = r0 * r0 + r1 * r1 + r2 * r2, z2 = xi2 * rr;
        const int small = z2 < VF_SMOOTH_Z2;
        const double e = vf_exp_nonpos(-z2);
        double ri, z, e_, E;
        vf_real_parts(small ? 1.0 : rr, xi, &ri, &z, &e_, &E);
        const double erfr = (1.0 - e * E) * ri;           /* erf(z) / r (large z) */
        double pe = ce[VF_SMOOTH_TERMS - 1], pg = cg[VF_SMOOTH_TERMS - 1], pb = cb[VF_SMOOTH_TERMS - 1];
        for (int n = VF_SMOOTH_TERMS - 2; n >= 0; --n) {
            pe = pe * z2 + ce[n];
            pg = pg * z2 + cg[n];
            pb = pb * z2 + cb[n];
        }
        if (want_s) {
            const double c = w[s] * c8;
            const double ci = ((small ? pe : erfr) + c2 * e) * c;
            const double ca = (small ? pg : (erfr - c2 * e) * ri * ri) * c;
            sg[s] = ci + ca * r0 * r0;
            sg[S + s] = ca * r0 * r1;
            sg[2 * S + s] = ca * r0 * r2;
            sg[3 * S + s] = ci + ca * r1 * r1;
            sg[4 * S + s] = ca * r1 * r2;
            sg[5 * S + s] = ci + ca * r2 * r2;
        }
        if (want_d) {
            const double ri2 = ri * ri;
            const double A = 4.0 * xi3 * VF_INV_SQPI * e * c8;
            const double b = (small ? pb : -6.0 * erfr * ri2 * ri2 + (12.0 * xi * ri2 * ri2 + 8.0 * xi3 * ri2) * e * VF_INV_SQPI) * c8;
            const double m0 = n0[s], m1 = n1[s], m2 = n2[s];
            const double rn = r0 * m0 + r1 * m1 + r2 * m2, c = b * rn;
            db[s] = -A * (rn + 2.0 * m0 * r0) + c * r0 * r0;
            db[S + s] = -A * (m0 * r1 + r0 * m1) + c * r0 * r1;
            db[2 * S + s] = -A * (m0 * r2 + r0 * m2) + c * r0 * r2;
            db[3 * S + s] = -A * (rn + 2.0 * m1 * r1) + c * r1 * r1;
            db[4 * S + s] = -A * (m1 * r2 + r1 * m2) + c * r1 * r2;
            db[5 * S + s] = -A * (rn + 2.0 * m2 * r2) + c * r2 * r2;
        }
    }
}

#define VF_SMOOTH_VARIANT(name, WS, WD)                                                                     \
    VF_CLONES static void name(const double *x, const double *y0, const double *y1, const double *y2,        \
                               const double *w, const double *n0, const double *n1, const double *n2,         \
                               ptrdiff_t S, double xi, double *sg, double *db)                                \
    {                                                                                                       \
        vf_smooth_row_generic(x, y0, y1, y2, w, n0, n1, n2, S, xi, WS, WD, sg, db);                         \
    }
VF_SMOOTH_VARIANT(vf_smooth_row_s, 1, 0)
VF_SMOOTH_VARIANT(vf_smooth_row_d, 0, 1)
VF_SMOOTH_VARIANT(vf_smooth_row_sd, 1, 1)

static void vf_smooth_row(const double *x, const double *y0, const double *y1, const double *y2, const double *w,
                          const double *n0, const double *n1, const double *n2, ptrdiff_t S, double xi,
                          double *sg, double *db)
{
    if (sg && db) vf_smooth_row_sd(x, y0, y1, y2, w, n0, n1, n2, S, xi, sg, db);
    else if (sg) vf_smooth_row_s(x, y0, y1, y2, w, n0, n1, n2, S, xi, sg, db);
    else if (db) vf_smooth_row_d(x, y0, y1, y2, w, n0, n1, n2, S, xi, sg, db);
}

/* the four real-space coefficients at r > 0 (tests): c[0] = a1, c[1] = a2, c[2] = A,
 * c[3] = B r^5 (ewald.pyx's tabulated functions), scalar */
static void vf_real_coefficients(double r, double xi, double *c)
{
    double ri, z, e, E;
    vf_real_parts(r * r, xi, &ri, &z, &e, &E);
    c[0] = e * (E - 2.0 * VF_INV_SQPI * z);
    c[1] = e * (E + 2.0 * VF_INV_SQPI * z);
    c[2] = 4.0 * xi * xi * xi * VF_INV_SQPI * e;
    c[3] = -2.0 * e * (3.0 * E + (6.0 * z + 4.0 * z * z * z) * VF_INV_SQPI);
}
#endif

/* One target against a contiguous range of sources [s0, s1): the Stokeslet (2.8) and the
 * lambda = 0 stresslet (2.9) sums of stokes.pyx, written for the compiler's vectorizer.
 *
 * - `#pragma omp simd reduction(...)` allows the sums over sources to be split into vector
 *   lanes (a reassociation the compiler may not do on its own without -ffast-math, which the
 *   singular quadrature cannot have);
 * - the exact-zero test (a source on the target contributes nothing) is a select, not a
 *   branch, so the loop body has no control flow;
 * - target_clones builds the function for the baseline (the -march of setup.py), AVX2+FMA
 *   (x86-64-v3) and AVX-512 (x86-64-v4); the loader picks the best one the CPU has (GNU ifunc).
 * Results agree with the scalar loop to rounding (lanes change the summation order; FMA
 * contracts products).
 * Where the CPU has AVX-512F/DQ the sums run in a loop written with intrinsics instead: 8
 * sources per step, de-interleaved by two permutes per component, 1/r from the 14-bit
 * estimate vrsqrt14pd refined by two Newton steps (relative error ~1e-16): the square root and
 * the division are the slowest instructions of the compiled loop (~2x fewer cycles per pair).
 * Where it has AVX2 and FMA but not AVX-512, the same loops on 4 lanes (pairsum_avx2.h).
 * vf_pairsum_set selects a path (tests compare the three). */
#ifndef VESFLOW_PAIRSUM_H
#define VESFLOW_PAIRSUM_H
#include <math.h>
#include <stddef.h>

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define VF_CLONES __attribute__((target_clones("default", "arch=x86-64-v3", "arch=x86-64-v4")))
#else
#define VF_CLONES
#endif

/* o[0:3] += (1/(8 pi)) sum_s (f_s / r + r (r . f_s) / r^3),  r = x - src_s */
VF_CLONES static void vf_stokeslet_range_clones(const double *src, const double *f, ptrdiff_t s0, ptrdiff_t s1,
                                         const double *x, double *o)
{
    const double x0 = x[0], x1 = x[1], x2 = x[2];
    double a0 = 0.0, a1 = 0.0, a2 = 0.0;
#pragma omp simd reduction(+ : a0, a1, a2)
    for (ptrdiff_t s = s0; s < s1; ++s) {
        const double r0 = x0 - src[3 * s], r1 = x1 - src[3 * s + 1], r2 = x2 - src[3 * s + 2];
        const double rr = r0 * r0 + r1 * r1 + r2 * r2;
        const double ri = rr > 0.0 ? 1.0 / sqrt(rr) : 0.0;
        const double f0 = f[3 * s], f1 = f[3 * s + 1], f2 = f[3 * s + 2];
        const double rf = (r0 * f0 + r1 * f1 + r2 * f2) * (ri * ri * ri);
        a0 += f0 * ri + r0 * rf;
        a1 += f1 * ri + r1 * rf;
        a2 += f2 * ri + r2 * rf;
    }
    const double c = 1.0 / (8.0 * M_PI);
    o[0] += a0 * c;
    o[1] += a1 * c;
    o[2] += a2 * c;
}

/* o[0:3] += -(3/(4 pi)) sum_s (r . nw_s)(r . g_s) r / r^5 */
VF_CLONES static void vf_stresslet_range_clones(const double *src, const double *nw, const double *g, ptrdiff_t s0,
                                         ptrdiff_t s1, const double *x, double *o)
{
    const double x0 = x[0], x1 = x[1], x2 = x[2];
    double a0 = 0.0, a1 = 0.0, a2 = 0.0;
#pragma omp simd reduction(+ : a0, a1, a2)
    for (ptrdiff_t s = s0; s < s1; ++s) {
        const double r0 = x0 - src[3 * s], r1 = x1 - src[3 * s + 1], r2 = x2 - src[3 * s + 2];
        const double rr = r0 * r0 + r1 * r1 + r2 * r2;
        const double ri = rr > 0.0 ? 1.0 / sqrt(rr) : 0.0;
        const double ri2 = ri * ri;
        const double c = (r0 * nw[3 * s] + r1 * nw[3 * s + 1] + r2 * nw[3 * s + 2])
                       * (r0 * g[3 * s] + r1 * g[3 * s + 1] + r2 * g[3 * s + 2]) * (ri2 * ri2 * ri);
        a0 += c * r0;
        a1 += c * r1;
        a2 += c * r2;
    }
    const double c = -3.0 / (4.0 * M_PI);
    o[0] += a0 * c;
    o[1] += a1 * c;
    o[2] += a2 * c;
}
/* The same two sums over the m sources of one vesicle stored planar: x[0..m), y[0..m), z[0..m)
 * at src, src + m, src + 2m (likewise the densities): the near blocks' layout (stokes.planar),
 * which the vector loops read without de-interleaving. */
VF_CLONES static void vf_stokeslet_planar_clones(const double *src, const double *f, ptrdiff_t m, const double *x,
                                                 double *o)
{
    const double x0 = x[0], x1 = x[1], x2 = x[2];
    double a0 = 0.0, a1 = 0.0, a2 = 0.0;
#pragma omp simd reduction(+ : a0, a1, a2)
    for (ptrdiff_t s = 0; s < m; ++s) {
        const double r0 = x0 - src[s], r1 = x1 - src[m + s], r2 = x2 - src[2 * m + s];
        const double rr = r0 * r0 + r1 * r1 + r2 * r2;
        const double ri = rr > 0.0 ? 1.0 / sqrt(rr) : 0.0;
        const double f0 = f[s], f1 = f[m + s], f2 = f[2 * m + s];
        const double rf = (r0 * f0 + r1 * f1 + r2 * f2) * (ri * ri * ri);
        a0 += f0 * ri + r0 * rf;
        a1 += f1 * ri + r1 * rf;
        a2 += f2 * ri + r2 * rf;
    }
    const double c = 1.0 / (8.0 * M_PI);
    o[0] += a0 * c;
    o[1] += a1 * c;
    o[2] += a2 * c;
}

VF_CLONES static void vf_stresslet_planar_clones(const double *src, const double *nw, const double *g, ptrdiff_t m,
                                                 const double *x, double *o)
{
    const double x0 = x[0], x1 = x[1], x2 = x[2];
    double a0 = 0.0, a1 = 0.0, a2 = 0.0;
#pragma omp simd reduction(+ : a0, a1, a2)
    for (ptrdiff_t s = 0; s < m; ++s) {
        const double r0 = x0 - src[s], r1 = x1 - src[m + s], r2 = x2 - src[2 * m + s];
        const double rr = r0 * r0 + r1 * r1 + r2 * r2;
        const double ri = rr > 0.0 ? 1.0 / sqrt(rr) : 0.0;
        const double ri2 = ri * ri;
        const double c = (r0 * nw[s] + r1 * nw[m + s] + r2 * nw[2 * m + s])
                       * (r0 * g[s] + r1 * g[m + s] + r2 * g[2 * m + s]) * (ri2 * ri2 * ri);
        a0 += c * r0;
        a1 += c * r1;
        a2 += c * r2;
    }
    const double c = -3.0 / (4.0 * M_PI);
    o[0] += a0 * c;
    o[1] += a1 * c;
    o[2] += a2 * c;
}
/* The vector path of the sums below, chosen once from the CPU (the best it has) or set by
 * vf_pairsum_set (stokes.set_vector_path, VESFLOW_SIMD): VF_PATH_AVX512 (AVX-512F/DQ),
 * VF_PATH_AVX2 (AVX2 + FMA: the same loops on 4 lanes), VF_PATH_GENERIC (the compiled loops). */
#define VF_PATH_GENERIC 0
#define VF_PATH_AVX2 1
#define VF_PATH_AVX512 2
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define VF_X86_PATHS 1
#include <immintrin.h>
static int vf_pairsum_mode = -1;     /* -1: not decided yet */

/* the best path this CPU can run */
static int vf_path_best(void)
{
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq"))
        return VF_PATH_AVX512;
    if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"))
        return VF_PATH_AVX2;
    return VF_PATH_GENERIC;
}
#else
static int vf_pairsum_mode = VF_PATH_GENERIC;
static int vf_path_best(void) { return VF_PATH_GENERIC; }
#endif

static int vf_pairsum_use(void)
{
    if (vf_pairsum_mode < 0)
        vf_pairsum_mode = vf_path_best();
    return vf_pairsum_mode;
}

/* select a path (VF_PATH_*); returns it, or -1 (nothing changed) if the CPU cannot run it */
static int vf_pairsum_set(int mode)
{
    if (mode < VF_PATH_GENERIC || mode > vf_path_best())
        return -1;
    vf_pairsum_mode = mode;
    return mode;
}

#ifdef VF_X86_PATHS
#define VF_PAIRSUM_AVX512 __attribute__((target("avx512f,avx512dq,fma")))

/* sources s .. s + m - 1 (m <= 8) of an (n, 3) array as three 8-lane columns (0 beyond m) */
VF_PAIRSUM_AVX512 static inline void vf_load3x8(const double *p, ptrdiff_t s, int m, __m512d *c0, __m512d *c1,
                                                __m512d *c2)
{
    static const int64_t i1[3][8] = {{0, 3, 6, 9, 12, 15, 0, 0}, {1, 4, 7, 10, 13, 0, 0, 0}, {2, 5, 8, 11, 14, 0, 0, 0}};
    static const int64_t i2[3][8] = {{0, 1, 2, 3, 4, 5, 10, 13}, {0, 1, 2, 3, 4, 8, 11, 14}, {0, 1, 2, 3, 4, 9, 12, 15}};
    const double *q = p + 3 * s;
    __m512d v0, v1, v2;
    if (m == 8) {
        v0 = _mm512_loadu_pd(q);
        v1 = _mm512_loadu_pd(q + 8);
        v2 = _mm512_loadu_pd(q + 16);
    } else {
        const int k = 3 * m;
        v0 = _mm512_maskz_loadu_pd((__mmask8)(k >= 8 ? 0xFF : (1u << k) - 1u), q);
        v1 = _mm512_maskz_loadu_pd((__mmask8)(k >= 16 ? 0xFF : k > 8 ? (1u << (k - 8)) - 1u : 0u), q + 8);
        v2 = _mm512_maskz_loadu_pd((__mmask8)(k > 16 ? (1u << (k - 16)) - 1u : 0u), q + 16);
    }
    *c0 = _mm512_permutex2var_pd(_mm512_permutex2var_pd(v0, _mm512_loadu_si512(i1[0]), v1), _mm512_loadu_si512(i2[0]), v2);
    *c1 = _mm512_permutex2var_pd(_mm512_permutex2var_pd(v0, _mm512_loadu_si512(i1[1]), v1), _mm512_loadu_si512(i2[1]), v2);
    *c2 = _mm512_permutex2var_pd(_mm512_permutex2var_pd(v0, _mm512_loadu_si512(i1[2]), v1), _mm512_loadu_si512(i2[2]), v2);
}

/* 1/sqrt(rr) for rr > 0, 0 for rr = 0 or a lane outside `valid` */
VF_PAIRSUM_AVX512 static inline __m512d vf_rsqrt_or_0(__m512d rr, __mmask8 valid)
{
    /* the estimate is 0 outside `pos`, and the Newton steps keep it 0 there (h y = 0) */
    const __mmask8 pos = _mm512_mask_cmp_pd_mask(valid, rr, _mm512_setzero_pd(), _CMP_GT_OQ);
    __m512d y = _mm512_maskz_rsqrt14_pd(pos, rr);
    const __m512d h = _mm512_mul_pd(rr, _mm512_set1_pd(0.5)), c = _mm512_set1_pd(1.5);
    y = _mm512_mul_pd(y, _mm512_fnmadd_pd(_mm512_mul_pd(h, y), y, c));
    return _mm512_mul_pd(y, _mm512_fnmadd_pd(_mm512_mul_pd(h, y), y, c));
}

VF_PAIRSUM_AVX512 static void vf_stokeslet_range_avx512(const double *src, const double *f, ptrdiff_t s0, ptrdiff_t s1,
                                                        const double *x, double *o)
{
    const __m512d X0 = _mm512_set1_pd(x[0]), X1 = _mm512_set1_pd(x[1]), X2 = _mm512_set1_pd(x[2]);
    __m512d a0 = _mm512_setzero_pd(), a1 = a0, a2 = a0;
    for (ptrdiff_t s = s0; s < s1; s += 8) {
        const int m = s1 - s >= 8 ? 8 : (int)(s1 - s);
        __m512d y0, y1, y2, f0, f1, f2;
        vf_load3x8(src, s, m, &y0, &y1, &y2);
        vf_load3x8(f, s, m, &f0, &f1, &f2);
        const __m512d r0 = _mm512_sub_pd(X0, y0), r1 = _mm512_sub_pd(X1, y1), r2 = _mm512_sub_pd(X2, y2);
        const __m512d rr = _mm512_fmadd_pd(r2, r2, _mm512_fmadd_pd(r1, r1, _mm512_mul_pd(r0, r0)));
        const __m512d ri = vf_rsqrt_or_0(rr, (__mmask8)(m == 8 ? 0xFF : (1u << m) - 1u));
        const __m512d rf = _mm512_mul_pd(_mm512_fmadd_pd(r2, f2, _mm512_fmadd_pd(r1, f1, _mm512_mul_pd(r0, f0))),
                                         _mm512_mul_pd(_mm512_mul_pd(ri, ri), ri));
        a0 = _mm512_fmadd_pd(f0, ri, _mm512_fmadd_pd(r0, rf, a0));
        a1 = _mm512_fmadd_pd(f1, ri, _mm512_fmadd_pd(r1, rf, a1));
        a2 = _mm512_fmadd_pd(f2, ri, _mm512_fmadd_pd(r2, rf, a2));
    }
    const double c = 1.0 / (8.0 * M_PI);
    o[0] += _mm512_reduce_add_pd(a0) * c;
    o[1] += _mm512_reduce_add_pd(a1) * c;
    o[2] += _mm512_reduce_add_pd(a2) * c;
}

VF_PAIRSUM_AVX512 static void vf_stresslet_range_avx512(const double *src, const double *nw, const double *g,
                                                        ptrdiff_t s0, ptrdiff_t s1, const double *x, double *o)
{
    const __m512d X0 = _mm512_set1_pd(x[0]), X1 = _mm512_set1_pd(x[1]), X2 = _mm512_set1_pd(x[2]);
    __m512d a0 = _mm512_setzero_pd(), a1 = a0, a2 = a0;
    for (ptrdiff_t s = s0; s < s1; s += 8) {
        const int m = s1 - s >= 8 ? 8 : (int)(s1 - s);
        __m512d y0, y1, y2, n0, n1, n2, g0, g1, g2;
        vf_load3x8(src, s, m, &y0, &y1, &y2);
        vf_load3x8(nw, s, m, &n0, &n1, &n2);
        vf_load3x8(g, s, m, &g0, &g1, &g2);
        const __m512d r0 = _mm512_sub_pd(X0, y0), r1 = _mm512_sub_pd(X1, y1), r2 = _mm512_sub_pd(X2, y2);
        const __m512d rr = _mm512_fmadd_pd(r2, r2, _mm512_fmadd_pd(r1, r1, _mm512_mul_pd(r0, r0)));
        const __m512d ri = vf_rsqrt_or_0(rr, (__mmask8)(m == 8 ? 0xFF : (1u << m) - 1u));
        const __m512d ri2 = _mm512_mul_pd(ri, ri);
        const __m512d rn = _mm512_fmadd_pd(r2, n2, _mm512_fmadd_pd(r1, n1, _mm512_mul_pd(r0, n0)));
        const __m512d rg = _mm512_fmadd_pd(r2, g2, _mm512_fmadd_pd(r1, g1, _mm512_mul_pd(r0, g0)));
        const __m512d c = _mm512_mul_pd(_mm512_mul_pd(rn, rg), _mm512_mul_pd(_mm512_mul_pd(ri2, ri2), ri));
        a0 = _mm512_fmadd_pd(c, r0, a0);
        a1 = _mm512_fmadd_pd(c, r1, a1);
        a2 = _mm512_fmadd_pd(c, r2, a2);
    }
    const double c = -3.0 / (4.0 * M_PI);
    o[0] += _mm512_reduce_add_pd(a0) * c;
    o[1] += _mm512_reduce_add_pd(a1) * c;
    o[2] += _mm512_reduce_add_pd(a2) * c;
}

/* one block of 8 sources (loaded, 0 beyond `valid`) added to the accumulators a[k] of K targets
 * X[k] (broadcast): the arithmetic shared by the multi-target sums below, whatever the loads */
VF_PAIRSUM_AVX512 static inline __attribute__((always_inline)) void vf_stokeslet_acc8(
    __m512d (*X)[3], int K, __m512d y0, __m512d y1, __m512d y2, __m512d f0, __m512d f1, __m512d f2,
    __mmask8 valid, __m512d (*a)[3])
{
    for (int k = 0; k < K; ++k) {
        const __m512d r0 = _mm512_sub_pd(X[k][0], y0), r1 = _mm512_sub_pd(X[k][1], y1),
                      r2 = _mm512_sub_pd(X[k][2], y2);
        const __m512d rr = _mm512_fmadd_pd(r2, r2, _mm512_fmadd_pd(r1, r1, _mm512_mul_pd(r0, r0)));
        const __m512d ri = vf_rsqrt_or_0(rr, valid);
        const __m512d rf = _mm512_mul_pd(_mm512_fmadd_pd(r2, f2, _mm512_fmadd_pd(r1, f1, _mm512_mul_pd(r0, f0))),
                                         _mm512_mul_pd(_mm512_mul_pd(ri, ri), ri));
        a[k][0] = _mm512_fmadd_pd(f0, ri, _mm512_fmadd_pd(r0, rf, a[k][0]));
        a[k][1] = _mm512_fmadd_pd(f1, ri, _mm512_fmadd_pd(r1, rf, a[k][1]));
        a[k][2] = _mm512_fmadd_pd(f2, ri, _mm512_fmadd_pd(r2, rf, a[k][2]));
    }
}

VF_PAIRSUM_AVX512 static inline __attribute__((always_inline)) void vf_stresslet_acc8(
    __m512d (*X)[3], int K, __m512d y0, __m512d y1, __m512d y2, __m512d n0, __m512d n1, __m512d n2,
    __m512d g0, __m512d g1, __m512d g2, __mmask8 valid, __m512d (*a)[3])
{
    for (int k = 0; k < K; ++k) {
        const __m512d r0 = _mm512_sub_pd(X[k][0], y0), r1 = _mm512_sub_pd(X[k][1], y1),
                      r2 = _mm512_sub_pd(X[k][2], y2);
        const __m512d rr = _mm512_fmadd_pd(r2, r2, _mm512_fmadd_pd(r1, r1, _mm512_mul_pd(r0, r0)));
        const __m512d ri = vf_rsqrt_or_0(rr, valid);
        const __m512d ri2 = _mm512_mul_pd(ri, ri);
        const __m512d rn = _mm512_fmadd_pd(r2, n2, _mm512_fmadd_pd(r1, n1, _mm512_mul_pd(r0, n0)));
        const __m512d rg = _mm512_fmadd_pd(r2, g2, _mm512_fmadd_pd(r1, g1, _mm512_mul_pd(r0, g0)));
        const __m512d c = _mm512_mul_pd(_mm512_mul_pd(rn, rg), _mm512_mul_pd(_mm512_mul_pd(ri2, ri2), ri));
        a[k][0] = _mm512_fmadd_pd(c, r0, a[k][0]);
        a[k][1] = _mm512_fmadd_pd(c, r1, a[k][1]);
        a[k][2] = _mm512_fmadd_pd(c, r2, a[k][2]);
    }
}

/* VF_MT targets at once against the same sources: the de-interleaved source vectors are
 * shared, each target's arithmetic is that of vf_*_range_avx512 (the same values, bit for bit) */
#define VF_MT 4
VF_PAIRSUM_AVX512 static void vf_stokeslet_multi_avx512(const double *src, const double *f, ptrdiff_t s0,
                                                        ptrdiff_t s1, const double *x, int K, double *o)
{
    __m512d X[VF_MT][3], a[VF_MT][3];
    for (int k = 0; k < K; ++k)
        for (int d = 0; d < 3; ++d) {
            X[k][d] = _mm512_set1_pd(x[3 * k + d]);
            a[k][d] = _mm512_setzero_pd();
        }
    for (ptrdiff_t s = s0; s < s1; s += 8) {
        const int m = s1 - s >= 8 ? 8 : (int)(s1 - s);
        const __mmask8 valid = (__mmask8)(m == 8 ? 0xFF : (1u << m) - 1u);
        __m512d y0, y1, y2, f0, f1, f2;
        vf_load3x8(src, s, m, &y0, &y1, &y2);
        vf_load3x8(f, s, m, &f0, &f1, &f2);
        vf_stokeslet_acc8(X, K, y0, y1, y2, f0, f1, f2, valid, a);
    }
    const double c = 1.0 / (8.0 * M_PI);
    for (int k = 0; k < K; ++k)
        for (int d = 0; d < 3; ++d)
            o[3 * k + d] += _mm512_reduce_add_pd(a[k][d]) * c;
}

VF_PAIRSUM_AVX512 static void vf_stresslet_multi_avx512(const double *src, const double *nw, const double *g,
                                                        ptrdiff_t s0, ptrdiff_t s1, const double *x, int K, double *o)
{
    __m512d X[VF_MT][3], a[VF_MT][3];
    for (int k = 0; k < K; ++k)
        for (int d = 0; d < 3; ++d) {
            X[k][d] = _mm512_set1_pd(x[3 * k + d]);
            a[k][d] = _mm512_setzero_pd();
        }
    for (ptrdiff_t s = s0; s < s1; s += 8) {
        const int m = s1 - s >= 8 ? 8 : (int)(s1 - s);
        const __mmask8 valid = (__mmask8)(m == 8 ? 0xFF : (1u << m) - 1u);
        __m512d y0, y1, y2, n0, n1, n2, g0, g1, g2;
        vf_load3x8(src, s, m, &y0, &y1, &y2);
        vf_load3x8(nw, s, m, &n0, &n1, &n2);
        vf_load3x8(g, s, m, &g0, &g1, &g2);
        vf_stresslet_acc8(X, K, y0, y1, y2, n0, n1, n2, g0, g1, g2, valid, a);
    }
    const double c = -3.0 / (4.0 * M_PI);
    for (int k = 0; k < K; ++k)
        for (int d = 0; d < 3; ++d)
            o[3 * k + d] += _mm512_reduce_add_pd(a[k][d]) * c;
}

/* K (<= VF_PMT, a constant where inlined) targets against the m planar sources of one vesicle:
 * the arithmetic of vf_stokeslet_multi_avx512 with three plain (masked at the end) loads per
 * array instead of loads and permutes, the same lanes: the same values, bit for bit */
#define VF_INLINE __attribute__((always_inline)) inline
/* targets per pass: a near block of 9 is 3 passes of 3 (4 + 4 + 1 measured 5-10% slower; 5 + 4 the same) */
#define VF_PMT 3
VF_PAIRSUM_AVX512 static VF_INLINE void vf_stokeslet_planar_k(const double *src, const double *f, ptrdiff_t m,
                                                              const double *x, const int K, double *o)
{
    __m512d X[VF_PMT][3], a[VF_PMT][3];
    for (int k = 0; k < K; ++k)
        for (int d = 0; d < 3; ++d) {
            X[k][d] = _mm512_set1_pd(x[3 * k + d]);
            a[k][d] = _mm512_setzero_pd();
        }
    for (ptrdiff_t s = 0; s < m; s += 8) {
        const __mmask8 valid = (__mmask8)(m - s >= 8 ? 0xFF : (1u << (m - s)) - 1u);
        const __m512d y0 = _mm512_maskz_loadu_pd(valid, src + s), y1 = _mm512_maskz_loadu_pd(valid, src + m + s),
                      y2 = _mm512_maskz_loadu_pd(valid, src + 2 * m + s);
        const __m512d f0 = _mm512_maskz_loadu_pd(valid, f + s), f1 = _mm512_maskz_loadu_pd(valid, f + m + s),
                      f2 = _mm512_maskz_loadu_pd(valid, f + 2 * m + s);
        vf_stokeslet_acc8(X, K, y0, y1, y2, f0, f1, f2, valid, a);
    }
    const double c = 1.0 / (8.0 * M_PI);
    for (int k = 0; k < K; ++k)
        for (int d = 0; d < 3; ++d)
            o[3 * k + d] += _mm512_reduce_add_pd(a[k][d]) * c;
}

VF_PAIRSUM_AVX512 static VF_INLINE void vf_stresslet_planar_k(const double *src, const double *nw, const double *g,
                                                              ptrdiff_t m, const double *x, const int K, double *o)
{
    __m512d X[VF_PMT][3], a[VF_PMT][3];
    for (int k = 0; k < K; ++k)
        for (int d = 0; d < 3; ++d) {
            X[k][d] = _mm512_set1_pd(x[3 * k + d]);
            a[k][d] = _mm512_setzero_pd();
        }
    for (ptrdiff_t s = 0; s < m; s += 8) {
        const __mmask8 valid = (__mmask8)(m - s >= 8 ? 0xFF : (1u << (m - s)) - 1u);
        const __m512d y0 = _mm512_maskz_loadu_pd(valid, src + s), y1 = _mm512_maskz_loadu_pd(valid, src + m + s),
                      y2 = _mm512_maskz_loadu_pd(valid, src + 2 * m + s);
        const __m512d n0 = _mm512_maskz_loadu_pd(valid, nw + s), n1 = _mm512_maskz_loadu_pd(valid, nw + m + s),
                      n2 = _mm512_maskz_loadu_pd(valid, nw + 2 * m + s);
        const __m512d g0 = _mm512_maskz_loadu_pd(valid, g + s), g1 = _mm512_maskz_loadu_pd(valid, g + m + s),
                      g2 = _mm512_maskz_loadu_pd(valid, g + 2 * m + s);
        vf_stresslet_acc8(X, K, y0, y1, y2, n0, n1, n2, g0, g1, g2, valid, a);
    }
    const double c = -3.0 / (4.0 * M_PI);
    for (int k = 0; k < K; ++k)
        for (int d = 0; d < 3; ++d)
            o[3 * k + d] += _mm512_reduce_add_pd(a[k][d]) * c;
}

/* any K: VF_PMT at a time, the rest by a version compiled for that count */
VF_PAIRSUM_AVX512 static void vf_stokeslet_planar_avx512(const double *src, const double *f, ptrdiff_t m,
                                                         const double *x, ptrdiff_t K, double *o)
{
    ptrdiff_t k = 0;
    for (; K - k >= VF_PMT; k += VF_PMT)
        vf_stokeslet_planar_k(src, f, m, x + 3 * k, VF_PMT, o + 3 * k);
    switch (K - k) {
    case 2: vf_stokeslet_planar_k(src, f, m, x + 3 * k, 2, o + 3 * k); break;
    case 1: vf_stokeslet_planar_k(src, f, m, x + 3 * k, 1, o + 3 * k); break;
    default: break;
    }
}

VF_PAIRSUM_AVX512 static void vf_stresslet_planar_avx512(const double *src, const double *nw, const double *g,
                                                         ptrdiff_t m, const double *x, ptrdiff_t K, double *o)
{
    ptrdiff_t k = 0;
    for (; K - k >= VF_PMT; k += VF_PMT)
        vf_stresslet_planar_k(src, nw, g, m, x + 3 * k, VF_PMT, o + 3 * k);
    switch (K - k) {
    case 2: vf_stresslet_planar_k(src, nw, g, m, x + 3 * k, 2, o + 3 * k); break;
    case 1: vf_stresslet_planar_k(src, nw, g, m, x + 3 * k, 1, o + 3 * k); break;
    default: break;
    }
}

/* Both layers at once (viscosity contrast: the near blocks need S[f] + D[g]): r, r^2 and 1/r
 * are shared, ~40 instead of ~57 vector operations per 8 sources and target; each lane does the
 * operations of vf_stokeslet_planar_k and vf_stresslet_planar_k, and o gets the Stokeslet sum
 * added first, then the stresslet's: bit for bit the two separate calls.  3 targets per pass
 * (measured as fast as 2, whose 12 accumulators and 12 source vectors fit the registers). */
#define VF_BMT 3
VF_PAIRSUM_AVX512 static VF_INLINE void vf_both_planar_k(const double *src, const double *f, const double *nw,
                                                         const double *g, ptrdiff_t m, const double *x, const int K,
                                                         double *o)
{
    __m512d X[VF_BMT][3], a[VF_BMT][3], b[VF_BMT][3];
    for (int k = 0; k < K; ++k)
        for (int d = 0; d < 3; ++d) {
            X[k][d] = _mm512_set1_pd(x[3 * k + d]);
            a[k][d] = _mm512_setzero_pd();
            b[k][d] = _mm512_setzero_pd();
        }
    for (ptrdiff_t s = 0; s < m; s += 8) {
        const __mmask8 valid = (__mmask8)(m - s >= 8 ? 0xFF : (1u << (m - s)) - 1u);
        const __m512d y0 = _mm512_maskz_loadu_pd(valid, src + s), y1 = _mm512_maskz_loadu_pd(valid, src + m + s),
                      y2 = _mm512_maskz_loadu_pd(valid, src + 2 * m + s);
        const __m512d f0 = _mm512_maskz_loadu_pd(valid, f + s), f1 = _mm512_maskz_loadu_pd(valid, f + m + s),
                      f2 = _mm512_maskz_loadu_pd(valid, f + 2 * m + s);
        const __m512d n0 = _mm512_maskz_loadu_pd(valid, nw + s), n1 = _mm512_maskz_loadu_pd(valid, nw + m + s),
                      n2 = _mm512_maskz_loadu_pd(valid, nw + 2 * m + s);
        const __m512d g0 = _mm512_maskz_loadu_pd(valid, g + s), g1 = _mm512_maskz_loadu_pd(valid, g + m + s),
                      g2 = _mm512_maskz_loadu_pd(valid, g + 2 * m + s);
        for (int k = 0; k < K; ++k) {
            const __m512d r0 = _mm512_sub_pd(X[k][0], y0), r1 = _mm512_sub_pd(X[k][1], y1),
                          r2 = _mm512_sub_pd(X[k][2], y2);
            const __m512d rr = _mm512_fmadd_pd(r2, r2, _mm512_fmadd_pd(r1, r1, _mm512_mul_pd(r0, r0)));
            const __m512d ri = vf_rsqrt_or_0(rr, valid);
            const __m512d rf = _mm512_mul_pd(_mm512_fmadd_pd(r2, f2, _mm512_fmadd_pd(r1, f1, _mm512_mul_pd(r0, f0))),
                                             _mm512_mul_pd(_mm512_mul_pd(ri, ri), ri));
            a[k][0] = _mm512_fmadd_pd(f0, ri, _mm512_fmadd_pd(r0, rf, a[k][0]));
            a[k][1] = _mm512_fmadd_pd(f1, ri, _mm512_fmadd_pd(r1, rf, a[k][1]));
            a[k][2] = _mm512_fmadd_pd(f2, ri, _mm512_fmadd_pd(r2, rf, a[k][2]));
            const __m512d ri2 = _mm512_mul_pd(ri, ri);
            const __m512d rn = _mm512_fmadd_pd(r2, n2, _mm512_fmadd_pd(r1, n1, _mm512_mul_pd(r0, n0)));
            const __m512d rg = _mm512_fmadd_pd(r2, g2, _mm512_fmadd_pd(r1, g1, _mm512_mul_pd(r0, g0)));
            const __m512d c = _mm512_mul_pd(_mm512_mul_pd(rn, rg), _mm512_mul_pd(_mm512_mul_pd(ri2, ri2), ri));
            b[k][0] = _mm512_fmadd_pd(c, r0, b[k][0]);
            b[k][1] = _mm512_fmadd_pd(c, r1, b[k][1]);
            b[k][2] = _mm512_fmadd_pd(c, r2, b[k][2]);
        }
    }
    const double cs = 1.0 / (8.0 * M_PI), cd = -3.0 / (4.0 * M_PI);
    for (int k = 0; k < K; ++k)
        for (int d = 0; d < 3; ++d) {
            o[3 * k + d] += _mm512_reduce_add_pd(a[k][d]) * cs;
            o[3 * k + d] += _mm512_reduce_add_pd(b[k][d]) * cd;
        }
}

VF_PAIRSUM_AVX512 static void vf_both_planar_avx512(const double *src, const double *f, const double *nw,
                                                    const double *g, ptrdiff_t m, const double *x, ptrdiff_t K,
                                                    double *o)
{
    ptrdiff_t k = 0;
    for (; K - k >= VF_BMT; k += VF_BMT)
        vf_both_planar_k(src, f, nw, g, m, x + 3 * k, VF_BMT, o + 3 * k);
    if (K - k == 2)
        vf_both_planar_k(src, f, nw, g, m, x + 3 * k, 2, o + 3 * k);
    else if (K - k == 1)
        vf_both_planar_k(src, f, nw, g, m, x + 3 * k, 1, o + 3 * k);
}
#include "pairsum_avx2.h"
#endif

/* The entry points: the path of vf_pairsum_use() (VF_X86_PATHS), else the compiled loops.
 * VF_DISPATCH(call512, call2) runs and returns from the caller where a vector path is on. */
#ifdef VF_X86_PATHS
#define VF_DISPATCH(call512, call2)                                                              \
    switch (vf_pairsum_use()) {                                                                  \
    case VF_PATH_AVX512: call512; return;                                                        \
    case VF_PATH_AVX2: call2; return;                                                            \
    default: break;                                                                              \
    }
#else
#define VF_DISPATCH(call512, call2)
#endif

/* o[0:3] += (1/(8 pi)) sum_s (f_s / r + r (r . f_s) / r^3),  r = x - src_s (r = 0 skipped) */
static void vf_stokeslet_range(const double *src, const double *f, ptrdiff_t s0, ptrdiff_t s1, const double *x,
                               double *o)
{
    VF_DISPATCH(vf_stokeslet_range_avx512(src, f, s0, s1, x, o), vf_stokeslet_multi_avx2(src, f, s0, s1, x, 1, o))
    vf_stokeslet_range_clones(src, f, s0, s1, x, o);
}

/* o[0:3] += -(3/(4 pi)) sum_s (r . nw_s)(r . g_s) r / r^5 (r = 0 skipped) */
static void vf_stresslet_range(const double *src, const double *nw, const double *g, ptrdiff_t s0, ptrdiff_t s1,
                               const double *x, double *o)
{
    VF_DISPATCH(vf_stresslet_range_avx512(src, nw, g, s0, s1, x, o),
                vf_stresslet_multi_avx2(src, nw, g, s0, s1, x, 1, o))
    vf_stresslet_range_clones(src, nw, g, s0, s1, x, o);
}
/* K targets x[3k..3k+2] (any K) against sources s0 .. s1: o[3k..] as vf_stokeslet_range for
 * each target (the same values), VF_MT targets at a time sharing the source loads */
static void vf_stokeslet_targets(const double *src, const double *f, ptrdiff_t s0, ptrdiff_t s1, const double *x,
                                 ptrdiff_t K, double *o)
{
    VF_DISPATCH(for (ptrdiff_t k = 0; k < K; k += VF_MT) vf_stokeslet_multi_avx512(
                    src, f, s0, s1, x + 3 * k, (int)(K - k < VF_MT ? K - k : VF_MT), o + 3 * k),
                vf_stokeslet_targets_avx2(src, f, s0, s1, x, K, o))
    for (ptrdiff_t k = 0; k < K; ++k)
        vf_stokeslet_range_clones(src, f, s0, s1, x + 3 * k, o + 3 * k);
}

static void vf_stresslet_targets(const double *src, const double *nw, const double *g, ptrdiff_t s0, ptrdiff_t s1,
                                 const double *x, ptrdiff_t K, double *o)
{
    VF_DISPATCH(for (ptrdiff_t k = 0; k < K; k += VF_MT) vf_stresslet_multi_avx512(
                    src, nw, g, s0, s1, x + 3 * k, (int)(K - k < VF_MT ? K - k : VF_MT), o + 3 * k),
                vf_stresslet_targets_avx2(src, nw, g, s0, s1, x, K, o))
    for (ptrdiff_t k = 0; k < K; ++k)
        vf_stresslet_range_clones(src, nw, g, s0, s1, x + 3 * k, o + 3 * k);
}

/* K targets x[3k..3k+2] against the m planar sources of one vesicle (src, f: x/y/z rows of m) */
static void vf_stokeslet_planar_targets(const double *src, const double *f, ptrdiff_t m, const double *x, ptrdiff_t K,
                                        double *o)
{
    VF_DISPATCH(vf_stokeslet_planar_avx512(src, f, m, x, K, o), vf_stokeslet_planar_avx2(src, f, m, x, K, o))
    for (ptrdiff_t k = 0; k < K; ++k)
        vf_stokeslet_planar_clones(src, f, m, x + 3 * k, o + 3 * k);
}

static void vf_stresslet_planar_targets(const double *src, const double *nw, const double *g, ptrdiff_t m,
                                        const double *x, ptrdiff_t K, double *o)
{
    VF_DISPATCH(vf_stresslet_planar_avx512(src, nw, g, m, x, K, o), vf_stresslet_planar_avx2(src, nw, g, m, x, K, o))
    for (ptrdiff_t k = 0; k < K; ++k)
        vf_stresslet_planar_clones(src, nw, g, m, x + 3 * k, o + 3 * k);
}

/* both layers: o[3k..] += S[f] then += D[g] at each of the K targets (the two calls above, fused) */
static void vf_both_planar_targets(const double *src, const double *f, const double *nw, const double *g, ptrdiff_t m,
                                   const double *x, ptrdiff_t K, double *o)
{
    VF_DISPATCH(vf_both_planar_avx512(src, f, nw, g, m, x, K, o), vf_both_planar_avx2(src, f, nw, g, m, x, K, o))
    for (ptrdiff_t k = 0; k < K; ++k) {
        vf_stokeslet_planar_clones(src, f, m, x + 3 * k, o + 3 * k);
        vf_stresslet_planar_clones(src, nw, g, m, x + 3 * k, o + 3 * k);
    }
}
#endif

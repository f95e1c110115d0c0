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
 * contracts products). */
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
VF_CLONES static void vf_stokeslet_range(const double *src, const double *f, ptrdiff_t s0, ptrdiff_t s1,
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
VF_CLONES static void vf_stresslet_range(const double *src, const double *nw, const double *g, ptrdiff_t s0,
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
#endif

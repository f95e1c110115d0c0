/* The near correction of one near (target, vesicle) pair as a fixed linear map of the density
 * (docs/explanation/method.md, section 5.2): the pair's correction is
 *
 *     sum_k c_k sum_s K(x_k, y_s) d_s,   x_0 the target (c_0 = -1: its smooth rule removed),
 *                                        x_1..x_8 the line points (c_l the Lagrange weights),
 *
 * over the m q-grid sources y_s of the vesicle, K the Stokeslet (density d_s = f_s w_s / mu) or
 * the stresslet (d_s = (1 - lambda) g_s, normal times weight nw_s).  Both kernels are symmetric
 * 3 x 3 matrices, so the combined kernel of the pair is 6 numbers per source,
 *
 *     R[a b][s] = sum_k c_k K_ab(x_k, y_s)      (ab = xx, xy, xz, yy, yz, zz),
 *
 * which these loops write (vectorized across the sources: `omp simd`, target_clones; square root
 * and division per evaluation, a source on a target skipped by the exact-zero select as in
 * pairsum.h).  vesflow.layerpot.nearmap projects the rows on the density's spherical-harmonic
 * coefficients once per set-up; a GMRES iteration is then 6 C multiply-adds per component and
 * pair instead of 9 m kernel evaluations. */
#ifndef VESFLOW_NEARMAP_H
#define VESFLOW_NEARMAP_H
#include <math.h>
#include <stddef.h>

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define VF_NM_CLONES __attribute__((target_clones("default", "arch=x86-64-v3", "arch=x86-64-v4")))
#else
#define VF_NM_CLONES
#endif

/* R (6 x m, row-major) = (1/(8 pi)) w_s sum_k c_k (delta / r + r r^T / r^3),  r = x_k - y_s;
 * src planar (x, y, z runs of m), w (m,), x (K, 3), c (K,).  One pass over the sources per
 * target (a plain vector loop; the 6 rows stay in the cache: 101 KB at m = 2112) */
VF_NM_CLONES static void vf_nearmap_stokeslet(const double *src, const double *w, ptrdiff_t m, const double *x,
                                              const double *c, int K, double *R)
{
    const double pre = 1.0 / (8.0 * M_PI);
    const double *y0 = src, *y1 = src + m, *y2 = src + 2 * m;
    double *R0 = R, *R1 = R + m, *R2 = R + 2 * m, *R3 = R + 3 * m, *R4 = R + 4 * m, *R5 = R + 5 * m;
    for (ptrdiff_t s = 0; s < 6 * m; ++s)
        R[s] = 0.0;
    for (int k = 0; k < K; ++k) {
        const double x0 = x[3 * k], x1 = x[3 * k + 1], x2 = x[3 * k + 2], ck = c[k];
#pragma omp simd
        for (ptrdiff_t s = 0; s < m; ++s) {
            const double r0 = x0 - y0[s], r1 = x1 - y1[s], r2 = x2 - y2[s];
            const double rr = r0 * r0 + r1 * r1 + r2 * r2;
            const double ri = rr > 0.0 ? 1.0 / sqrt(rr) : 0.0;
            const double ci = ck * ri, c3 = ci * ri * ri;
            R0[s] += ci + r0 * r0 * c3;
            R1[s] += r0 * r1 * c3;
            R2[s] += r0 * r2 * c3;
            R3[s] += ci + r1 * r1 * c3;
            R4[s] += r1 * r2 * c3;
            R5[s] += ci + r2 * r2 * c3;
        }
    }
#pragma omp simd
    for (ptrdiff_t s = 0; s < m; ++s) {
        const double ws = w[s] * pre;
        R0[s] *= ws;
        R1[s] *= ws;
        R2[s] *= ws;
        R3[s] *= ws;
        R4[s] *= ws;
        R5[s] *= ws;
    }
}

/* R (6 x m) = -(3/(4 pi)) sum_k c_k (r . nw_s) r r^T / r^5;  src, nw planar, x (K, 3), c (K,) */
VF_NM_CLONES static void vf_nearmap_stresslet(const double *src, const double *nw, ptrdiff_t m, const double *x,
                                              const double *c, int K, double *R)
{
    const double pre = -3.0 / (4.0 * M_PI);
    const double *y0 = src, *y1 = src + m, *y2 = src + 2 * m, *n0 = nw, *n1 = nw + m, *n2 = nw + 2 * m;
    double *R0 = R, *R1 = R + m, *R2 = R + 2 * m, *R3 = R + 3 * m, *R4 = R + 4 * m, *R5 = R + 5 * m;
    for (ptrdiff_t s = 0; s < 6 * m; ++s)
        R[s] = 0.0;
    for (int k = 0; k < K; ++k) {
        const double x0 = x[3 * k], x1 = x[3 * k + 1], x2 = x[3 * k + 2], ck = c[k] * pre;
#pragma omp simd
        for (ptrdiff_t s = 0; s < m; ++s) {
            const double r0 = x0 - y0[s], r1 = x1 - y1[s], r2 = x2 - y2[s];
            const double rr = r0 * r0 + r1 * r1 + r2 * r2;
            const double ri = rr > 0.0 ? 1.0 / sqrt(rr) : 0.0;
            const double ri2 = ri * ri;
            const double t = ck * (r0 * n0[s] + r1 * n1[s] + r2 * n2[s]) * (ri2 * ri2 * ri);
            R0[s] += r0 * r0 * t;
            R1[s] += r0 * r1 * t;
            R2[s] += r0 * r2 * t;
            R3[s] += r1 * r1 * t;
            R4[s] += r1 * r2 * t;
            R5[s] += r2 * r2 * t;
        }
    }
}

/* o[0:3] += A d:  A (6 x n, the symmetric 3 x 3 blocks xx xy xz yy yz zz per coefficient),
 * d (3 x n, the components' coefficients) */
VF_NM_CLONES static void vf_nearmap_apply(const double *A, const double *d, ptrdiff_t n, double *o)
{
    double u0 = 0.0, u1 = 0.0, u2 = 0.0;
#pragma omp simd reduction(+ : u0, u1, u2)
    for (ptrdiff_t j = 0; j < n; ++j) {
        const double d0 = d[j], d1 = d[n + j], d2 = d[2 * n + j];
        const double axx = A[j], axy = A[n + j], axz = A[2 * n + j], ayy = A[3 * n + j], ayz = A[4 * n + j],
                     azz = A[5 * n + j];
        u0 += axx * d0 + axy * d1 + axz * d2;
        u1 += axy * d0 + ayy * d1 + ayz * d2;
        u2 += axz * d0 + ayz * d1 + azz * d2;
    }
    o[0] += u0;
    o[1] += u1;
    o[2] += u2;
}
#endif

/* The real-space sum of ewaldsum.h on CPUs with AVX2 and FMA (the VF_PATH_AVX2 path): its
 * portable loop compiled for x86-64-v3 (4 lanes, FMA; square root and division per pair). */
#ifndef VESFLOW_EWALDSUM_AVX2_H
#define VESFLOW_EWALDSUM_AVX2_H

#define VF_REAL_V3(name, MI, SL, DL)                                                                       \
    __attribute__((target("arch=x86-64-v3"))) static void name(                                            \
        const double *y, const double *d, ptrdiff_t ld, const vf_range *rg, ptrdiff_t nr, double xi,         \
        double rc2, const double *mL, const double *iL, double *o)                                         \
    {                                                                                                      \
        vf_ewald_real_generic(y, d, ld, rg, nr, xi, rc2, mL, iL, MI, SL, DL, o);                           \
    }
VF_REAL_V3(vf_ewald_real_s_v3, 0, 1, 0)
VF_REAL_V3(vf_ewald_real_d_v3, 0, 0, 1)
VF_REAL_V3(vf_ewald_real_sd_v3, 0, 1, 1)
VF_REAL_V3(vf_ewald_real_s_mi_v3, 1, 1, 0)
VF_REAL_V3(vf_ewald_real_d_mi_v3, 1, 0, 1)
VF_REAL_V3(vf_ewald_real_sd_mi_v3, 1, 1, 1)

static void vf_ewald_real_avx2(const double *y, const double *d, ptrdiff_t ld, const vf_range *rg, ptrdiff_t nr,
                               double xi, double rc2, const double *mL, const double *iL, int mi, int sl, int dl,
                               double *o)
{
    if (mi) {
        if (sl && dl) vf_ewald_real_sd_mi_v3(y, d, ld, rg, nr, xi, rc2, mL, iL, o);
        else if (sl) vf_ewald_real_s_mi_v3(y, d, ld, rg, nr, xi, rc2, mL, iL, o);
        else vf_ewald_real_d_mi_v3(y, d, ld, rg, nr, xi, rc2, mL, iL, o);
    } else {
        if (sl && dl) vf_ewald_real_sd_v3(y, d, ld, rg, nr, xi, rc2, mL, iL, o);
        else if (sl) vf_ewald_real_s_v3(y, d, ld, rg, nr, xi, rc2, mL, iL, o);
        else vf_ewald_real_d_v3(y, d, ld, rg, nr, xi, rc2, mL, iL, o);
    }
}
#endif

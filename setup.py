"""Build of vesflow's Cython kernels (listed by name; see vesflow/_kernels/)."""
import numpy
from setuptools import Extension, setup
from Cython.Build import cythonize

KERNELS = [
    "stokes",      # direct Stokeslet / stresslet sums, source -> target (far field, near/self smooth rules)
    "search",      # cell-list near-pair search
    "series",      # spherical-harmonic series at arbitrary points (projections)
    "ewald",       # real-space part of the spectral Ewald sums (cell lists)
]

HEADERS = ["pairsum.h", "pairsum_avx2.h", "ewaldsum.h", "ewaldsum_avx2.h"]

compile_args = ["-O3", "-fopenmp", "-march=x86-64-v2", "-fno-math-errno"]
# no -ffast-math: the singular quadrature needs exact cancellation.  -fno-math-errno changes no
# result (sqrt of a negative number does not set errno) but lets sqrt vectorize (pairsum.h)
extensions = [
    Extension(
        f"vesflow._kernels.{name}",
        [f"vesflow/_kernels/{name}.pyx"],
        include_dirs=[numpy.get_include(), "vesflow/_kernels"],
        extra_compile_args=compile_args,
        extra_link_args=["-fopenmp"],
        define_macros=[("NPY_NO_DEPRECATED_API", "NPY_1_7_API_VERSION")],
        # a changed header or flag rebuilds the kernel (the up-to-date check compares times)
        depends=[f"vesflow/_kernels/{h}" for h in HEADERS] + ["setup.py"],
    )
    for name in KERNELS
]

setup(
    ext_modules=cythonize(
        extensions,
        language_level=3,
        compiler_directives={"boundscheck": False, "wraparound": False, "cdivision": True,
                             "initializedcheck": False},
    ),
)

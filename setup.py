"""Build of vesflow's Cython kernels (listed by name; see vesflow/_kernels/)."""
import os

import numpy
from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext
from setuptools.modified import newer_group
from Cython.Build import cythonize

KERNELS = [
    "stokes",      # direct Stokeslet / stresslet sums, source -> target (far field, near/self smooth rules)
    "search",      # cell-list near-pair search
    "series",      # spherical-harmonic series at arbitrary points (projections)
    "ewald",       # real-space part of the spectral Ewald sums (cell lists)
    "spread",      # ES-kernel spreading / interpolation on a box of a periodic grid (distributed Ewald grid)
]

HEADERS = ["pairsum.h", "pairsum_avx2.h", "nearmap.h", "ewaldsum.h", "ewaldsum_avx2.h", "ewald_cells.pxi"]   # and includes

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
        depends=[f"vesflow/_kernels/{h}" for h in HEADERS] + [f"vesflow/_kernels/{name}.pyx", "setup.py"],
    )
    for name in KERNELS
]



class BuildKernels(build_ext):
    """build_ext that takes a kernel already built in place (`setup.py build_ext --inplace`, the
    editable install) when it is newer than its sources, headers and setup.py, instead of
    compiling it again: the wheel and a second editable build copy it (same sources, same
    flags).  --force compiles."""

    def build_extension(self, ext):
        here = self.get_ext_filename(ext.name)          # vesflow/_kernels/NAME.<tag>.so
        target = self.get_ext_fullpath(ext.name)
        if (not self.inplace and not self.force and os.path.exists(here)
                and os.path.abspath(here) != os.path.abspath(target)
                and not newer_group(list(ext.sources) + list(ext.depends), here)):
            self.mkpath(os.path.dirname(target))
            self.copy_file(here, target)
            return
        super().build_extension(ext)


setup(
    cmdclass={"build_ext": BuildKernels},
    ext_modules=cythonize(
        extensions,
        language_level=3,
        compiler_directives={"boundscheck": False, "wraparound": False, "cdivision": True,
                             "initializedcheck": False},
    ),
)

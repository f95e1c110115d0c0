"""The vector paths of the compiled pair sums (pairsum.h, ewaldsum.h) and their choice.

Each kernel module (stokes, ewald) runs one of

    avx512   AVX-512F/DQ intrinsics, 8 lanes (the default where the CPU has them)
    avx2     AVX2 + FMA intrinsics, 4 lanes (the default on x86-64-v3 CPUs without AVX-512)
    generic  the loops compiled for the vectorizer (the loader picks the best clone the CPU has)

chosen once at import: the best the CPU runs, or the one named by the environment variable
VESFLOW_SIMD (for timings and tests: the values agree to rounding, ~1e-13 relative).
``set_vector_path`` of each module changes it, ``vector_path`` says which one runs.
"""
import os

from vesflow.errors import SettingsError

PATHS = ("generic", "avx2", "avx512")        # index = VF_PATH_* of pairsum.h
ENV = "VESFLOW_SIMD"


def index(path, best):
    """The VF_PATH_* index of `path` (a name of PATHS; True: the best the CPU runs, `best`;
    False: generic), checked against the CPU's best; a SettingsError naming the valid ones."""
    if path is True:
        return best
    if path is False:
        return 0
    if path not in PATHS:
        raise SettingsError(f"vector path {path!r}: must be one of {', '.join(PATHS)}")
    i = PATHS.index(path)
    if i > best:
        raise SettingsError(f"vector path {path!r}: this CPU runs only {', '.join(PATHS[:best + 1])}")
    return i


def from_environment(best):
    """The path VESFLOW_SIMD names (its index), or the CPU's best when it is unset or empty."""
    value = os.environ.get(ENV, "").strip().lower()
    if not value:
        return best
    try:
        return index(value, best)
    except SettingsError as e:
        raise SettingsError(f"{ENV}={value}: {str(e).split(': ', 1)[1]}") from None

"""The layout of a run file: frame fields, step columns and reasons, chunking."""
from __future__ import annotations

import datetime

import h5py
import numpy as np

FORMAT_VERSION = 1

# Code -> (name, meaning) of /steps/reason.  Names or codes are accepted by write_steps.
STEP_REASONS = {
    0: ("accepted", "step accepted"),
    1: ("error_estimate", "rejected: the error estimate is above the tolerance"),
    2: ("ksp", "rejected: a KSP solve did not converge"),
    3: ("collision", "rejected: surfaces touch or overlap"),
    4: ("invariants", "rejected: the area or volume drift is above the tolerance"),
    5: ("nonfinite", "rejected: NaN or Inf in the new state"),
    6: ("dt_min", "failed: dt fell below its minimum, the run stops"),
    -1: ("other", "rejected for another reason"),
}
REASON_CODE = {name: code for code, (name, _) in STEP_REASONS.items()}
REASON_DTYPE = h5py.enum_dtype(REASON_CODE, basetype="i1")

# name -> (dtype, column description)
STEP_COLUMNS = {
    "time": ("f8", "simulated time at the START of the attempted step"),
    "dt": ("f8", "attempted step size"),
    "accepted": ("i1", "1 if the step was accepted, 0 if rejected"),
    "ksp_its": ("i4", "GMRES iterations of the step (sum over its solves)"),
    "error_estimate": ("f8", "error estimate used by the adaptivity (NaN if none)"),
    "reason": (REASON_DTYPE, "why the step was accepted or rejected: see attribute reason_table"),
    "q_self": ("i2", "upsampled degree of the singular quadrature used by the step (0: not recorded)"),
    "q_near": ("i2", "upsampled degree of the near-singular and far-field rules used by the step (0: not recorded)"),
}
TIMING_KEYS = ("setup", "self", "near", "far", "repar", "other", "total")

# name -> (trailing shape given N, M, C, description, units, compressed)
FRAME_FIELDS = {
    "time": (lambda n, m, c: (), "simulated time of the frame", "time", False),
    "points": (lambda n, m, c: (n, m, 3), "surface points on the p-grid", "length", True),
    "coefficients": (lambda n, m, c: (n, 3, c), "SH coefficients of x, y, z (layout: vesflow/sph.py)",
                     "length", True),
    "tension": (lambda n, m, c: (n, m), "membrane tension on the p-grid", "force/length", True),
    "area": (lambda n, m, c: (n,), "surface area", "length^2", False),
    "volume": (lambda n, m, c: (n,), "enclosed volume", "length^3", False),
    "centroid": (lambda n, m, c: (n, 3), "centroid of the enclosed volume", "length", False),
    "bending_energy": (lambda n, m, c: (n,), "kappa_b * integral(H^2 dA)", "energy", False),
}
OPTIONAL_FIELDS = {
    "velocity": (lambda n, m, c: (n, m, 3), "surface velocity on the p-grid", "length/time", True),
    "poles": (lambda n, m, c: (n, 2, 3), "north and south pole points (for pictures)", "length", True),
    "bending_energy_density": (lambda n, m, c: (n, m), "bending energy per unit area kappa_b H^2 on the p-grid "
                               "(its integral over the surface is bending_energy)", "energy/length^2", True),
    "image": (lambda n, m, c: (n, 3), "periodic runs: lattice vector / L taken off each vesicle by the "
              "wrap into [0, L)^3 (unwrapped position = stored + L image)", "1", False),
}
# fields that are not float64: name -> (dtype, fill value of frames written without them)
FIELD_DTYPES = {"image": ("i8", 0)}
_CHUNK_BYTES = 1 << 20  # about 1 MiB per chunk


def grid_size(p):
    """Number of p-grid points per vesicle, M = 2p(p+1)."""
    return 2 * p * (p + 1)


def n_coefficients(p):
    """Number of SH coefficients of a scalar, C = (p+1)^2 - 1 (the m = p sine mode is dropped)."""
    return (p + 1) ** 2 - 1


def chunks(shape, compressed):
    """Chunks along F.  Compressed (per-point) fields: one frame per chunk, split along N
    above ~1 MiB, so that writing a frame never rewrites a compressed chunk.  Small
    per-vesicle fields: as many frames as fit in ~64 KiB."""
    row = int(np.prod(shape, dtype=np.int64)) * 8
    if compressed:
        per_ves = max(1, row // max(shape[0], 1))
        nv = int(max(1, min(shape[0], _CHUNK_BYTES // per_ves)))
        return (1, nv) + tuple(shape[1:])
    nf = int(max(1, min(1024, (_CHUNK_BYTES // 16) // max(row, 1))))
    return (nf,) + tuple(shape)


def now():
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def time_tol(t):
    return 1e-9 * max(1.0, abs(float(t)))

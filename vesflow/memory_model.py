"""Memory of a run: what a Stepper holds, counted from its arrays (`held_memory`), and the
model of the bytes per vesicle at a step's peak that `vesflow check` and the memory-aware
choices use (`memory_per_vesicle`, `memory_choices`; docs/explanation/parallel.md, "Memory")."""
from __future__ import annotations

import os

import numpy as np

from . import sph
from .layerpot.evaluator import NEAR_MAP_MB
from .layerpot.nearmap import map_bytes_per_pair


# ------------------------------------------------------------------ what a run holds (measured)
def array_bytes(obj, seen=None, depth=0):
    """Bytes of the numpy arrays reachable from obj (attributes, containers), each buffer
    counted once (a view counts its base; `seen`: ids already counted, shared across calls).
    The transforms' tables (sph.Transform, cached per degree for the whole process) are left out."""
    seen = set() if seen is None else seen
    if obj is None or depth > 12 or isinstance(obj, (int, float, str, bytes, bool, type)):
        return 0
    if isinstance(obj, np.ndarray):
        while isinstance(obj.base, np.ndarray):
            obj = obj.base
        if id(obj) in seen:
            return 0
        seen.add(id(obj))
        return int(obj.nbytes)
    if id(obj) in seen or isinstance(obj, sph.Transform):
        return 0
    seen.add(id(obj))
    if isinstance(obj, dict):
        items = obj.values()
    elif isinstance(obj, (list, tuple, set, frozenset)):
        items = obj
    elif hasattr(obj, "__dict__") and not callable(obj):
        items = vars(obj).values()
    else:
        return 0
    return sum(array_bytes(x, seen, depth + 1) for x in items)


def held_memory(stepper):
    """Bytes a Stepper holds between solves, by category (each array counted once, in the
    first category that reaches it): the preconditioner's parts and LU factors, and for each
    cached set of layer potentials its self operators, the Ewald own smooth operators, the
    near pairs, the far field (Ewald grids) and the rest (sources, targets); then the state.
    The number of cached layer potentials is `layer_potentials`."""
    seen, out = set(), {}
    ctx = getattr(stepper, "_pc_context", None)
    out["pc_parts"] = array_bytes(getattr(ctx, "parts", None), seen)
    out["pc_factors"] = array_bytes(getattr(ctx, "factors", None), seen) + array_bytes(getattr(ctx, "lu", None), seen)
    lps = [lp for _, lp in stepper._lp_cache]
    for extra in (getattr(stepper, "lp_last", None), getattr(stepper, "lp_current", None)):
        if extra is not None and all(extra is not lp for lp in lps):
            lps.append(extra)
    for key, attr in (("self", "self_ops"), ("own", "own_ops"), ("near", "near"), ("far", "far")):
        out[key] = sum(array_bytes(getattr(lp, attr, None), seen) for lp in lps)
    out["sources"] = sum(array_bytes(lp, seen) for lp in lps)
    out["pc_other"] = array_bytes(ctx, seen)
    out["state"] = array_bytes(stepper, seen)
    out["layer_potentials"] = len(lps)
    out["total"] = sum(v for k, v in out.items() if k != "layer_potentials")
    return out


# ------------------------------------------------------------------ memory per vesicle (modelled)
# Measured (benchmarks/memory_per_vesicle.py, p = 16; docs/explanation/parallel.md "Memory"):
# bytes per near pair held (NearPairs: basis row C, line points, weights, projection) beyond C x 8,
# per q-grid source point and per geometry grid point of the layer potentials' surfaces, the
# set-up's transient per vesicle at the peak, and the process's base (interpreter, libraries,
# PETSc, the transforms' and rotations' tables)
NEAR_PAIR_EXTRA_BYTES = 417      # NearPairs: 2721 B per pair at p = 16, C x 8 = 2304 of it the basis row
SOURCE_POINT_BYTES = 112         # points, normals x weights (and planar copies), weights, ids
GEOMETRY_POINT_BYTES = 330       # Geometry: 41 doubles per point (the q_far and p grids of each held surface)
TRANSIENT_FRACTION = 0.07        # the step's traced peak over the arrays held after it (75.1 / 70.4 MB, N = 16)
SETUP_THREAD_BYTES = 120 * 2 ** 20   # one vesicle's block assembly (force matrices, A0) per set-up thread, p = 16
EWALD_GRIDS, EWALD_GRIDS_APPLY = 5, 4     # complex mode grids held per set of layer potentials, and while applied
NEAR_PAIRS_ASSUMED = 500       # near pairs per vesicle when they are not counted (1408 cells at 35 %: 508)
MEMORY_OPTIONS = ("pc_precision", "ewald_own", "pc_factors", "setup_cache", "pc_parts", "self_precision", "near_map_mb")


def factor_sets(o):
    """The LU factor sets a step uses (one per distinct dt within precond.DT_MATCH): sdc its
    distinct substeps and the velocity solves (dt = 0), euler with doubling dt and dt / 2, else 1;
    at most -ves_pc_factors."""
    ts = o.get("ts_type") or ("euler" if o.get("coupling") == "explicit" else "sdc")
    if ts == "sdc":      # Radau IIA: n - 1 substeps of different lengths; Gauss-Lobatto: symmetric
        n = int(o.get("ts_sdc_nodes") or 3)
        used = 1 + ((n - 1) if (o.get("ts_sdc_quadrature") or "radau") == "radau" else n // 2)
    else:
        used = 2 if (o.get("adapt") or "doubling") == "doubling" else 1
    return min(used, int(o.get("pc_factors") or 3))


def layer_potentials_held(o):
    """Sets of layer potentials a step holds: sdc the step's start's and the current one's
    (Stepper.lp_pinned; one with -ves_setup_cache current), euler one."""
    ts = o.get("ts_type") or ("euler" if o.get("coupling") == "explicit" else "sdc")
    return 2 if ts == "sdc" and o.get("setup_cache") != "current" else 1


def memory_per_vesicle(p, q, o, double_layer=False, near_pairs_per_vesicle=0.0, own_smooth=False, own_bytes=8,
                       n_vesicles=2):
    """Bytes per vesicle a run holds at a step's peak, by category (dict): the self operators
    and the Ewald own smooth operators (per held set of layer potentials), the preconditioner's
    parts (BlockParts: 15 C^2, 24 C^2 with a contrast; none with -ves_pc_parts drop) and LU factor
    sets (factor_sets), the near pairs, sources and surface geometry of the held layer
    potentials, and the set-up's transient.  o: resolved options (read_options; a dict)."""
    C, Mq = (p + 1) ** 2 - 1, 2 * q * (q + 1)
    n_ops = 2 if double_layer else 1
    self_bytes = 4 if o.get("self_precision") == "single" else 8
    pc_bytes = 4 if o.get("pc_precision") == "single" else 8
    lps = layer_potentials_held(o)
    out = {"self": lps * n_ops * (3 * C) ** 2 * self_bytes,
           "own": lps * n_ops * (3 * C) ** 2 * own_bytes if own_smooth else 0,
           "pc_parts": 0 if o.get("pc_parts") == "drop" else (24 if double_layer else 15) * C ** 2 * pc_bytes,
           "pc_factors": factor_sets(o) * ((4 * C) ** 2 * pc_bytes + 4 * C * 4),
           "near": lps * near_pairs_per_vesicle * (C * 8 + NEAR_PAIR_EXTRA_BYTES),
           # the near pairs' maps (vesflow.layerpot.nearmap), within -ves_near_map_mb per set
           "near_maps": lps * min(near_pairs_per_vesicle * map_bytes_per_pair(C, n_ops),
                                  _near_map_budget(o) / max(n_vesicles, 1)),
           "sources": (lps * Mq * SOURCE_POINT_BYTES if n_vesicles > 1 else 0)
           + (lps + 1) * GEOMETRY_POINT_BYTES * (Mq + 2 * p * (p + 1))}
    out["transient"] = int(TRANSIENT_FRACTION * sum(out.values()))
    return out


def _near_map_budget(o):
    """Bytes of near maps per set of layer potentials (-ves_near_map_mb, MB)."""
    mb = o.get("near_map_mb")
    return float(NEAR_MAP_MB if mb is None else mb) * 1e6


def available_memory(limit_gib=None):
    """(bytes, where from): -ves_memory_limit (GiB) when given, else MemAvailable of /proc/meminfo,
    else the physical memory; (None, "unknown") when none can be read."""
    if limit_gib is not None:
        return int(float(limit_gib) * 2 ** 30), "-ves_memory_limit"
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "MemAvailable"
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"), "physical memory"
    except (ValueError, OSError, AttributeError):
        return None, "unknown"


def memory_choices(o):
    """The memory options to try, cumulatively, cheapest first, that the user did not give
    (o.given): float32 preconditioner (fgmres keeps double's accuracy), no Ewald own smooth
    operators (a dearer iteration), one LU factor set (a factorization per new dt), one set of
    layer potentials (2 more set-ups per sdc step), the parts dropped (the blocks rebuilt per new
    dt), float32 self operators (the operator rounded: 2.8e-8 of a solve), no near maps (the
    near pairs summed again at every iteration: 10-26 us per pair instead of 0.9)."""
    given = getattr(o, "given", frozenset())
    steps = [("pc_precision", "single"), ("ewald_own", "subtract"), ("pc_factors", 1), ("setup_cache", "current"),
             ("pc_parts", "drop"), ("self_precision", "single"), ("near_map_mb", 0.0)]
    return [(k, v) for k, v in steps if f"-ves_{k}" not in given and o.get(k) != v]

"""Measured machine constants of the cost model (vesflow.costs: `vesflow check`'s predicted times).

Read ONLY by the cost model's predictions.  No numerical choice of a run reads them: the far-field
backend, the Ewald cutoff, the own-vesicle mode and the preconditioner's rebuild are fixed rules
with frozen weights of their own (vesflow.costs.decision_rules; docs/explanation/calibration.md),
so that a run of the same options takes the same steps on every machine.

The values: a calibration file if there is one (JSON written by benchmarks/calibrate.py, at
$VESFLOW_CALIBRATION, else ~/.cache/vesflow/calibration.json), else DEFAULTS, the development
machine's figures (2 cores, one thread, CPU seconds).  Each constant, with how it is measured:

    self_gemv_bytes_per_s   bytes of the self operators streamed per second by their batched GEMV
                            (N (3C)^2 float64 entries per apply)
    forces_s                (a, b): seconds per vesicle per GMRES iteration of the membrane forces
                            and transforms, a + b p^3 (StepOperator.membrane_force + divergence)
    self_setup_s            (t16, e): seconds per vesicle to assemble the singular self operator
                            S at q = 2p, t16 (p / 16)^e (SelfOperators)
    pc_setup_s              (t16, e): seconds per vesicle to build and factor the block
                            preconditioner's block, t16 (p / 16)^e (BlockJacobi.block_parts + LU)
    near_s_per_eval         seconds per near kernel evaluation (target or line point, source) of
                            the near correction in blocks, one thread
    direct_s_per_pair       seconds per (target, source) pair of the direct Stokeslet sum, one thread
    fmm_s_per_point         [(eps, seconds per point)]: fmm3dpy's Stokes FMM per source + target
                            point at accuracy eps (interpolated in log eps, clamped outside)
    ewald                   the Ewald sum's parts (vesflow.layerpot.ewald._predicted_parts): real
                            space per pair inside rc ("pair"), per target ("target"), per own pair
                            ("own_pair"); NUFFT spreading per point per kernel width cubed
                            ("nufft_point"); FFT per fine-grid point per log2 ("fft_point") with the
                            large-grid growth exponent ("fft_growth"); k-space per mode ("mode")
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, fields

from .errors import SettingsError

ENV = "VESFLOW_CALIBRATION"
DEFAULT_PATH = os.path.join("~", ".cache", "vesflow", "calibration.json")
FILE_VERSION = 1
EWALD_KEYS = ("pair", "target", "own_pair", "nufft_point", "fft_point", "fft_growth", "mode")


@dataclass(frozen=True)
class Calibration:
    """One machine's constants (module docstring); ``source``: the file they came from, or "defaults"."""

    self_gemv_bytes_per_s: float = 2e10
    forces_s: tuple = (8.0e-5, 1.0e-7)
    self_setup_s: tuple = (0.088, 4.0)
    pc_setup_s: tuple = (0.26, 4.0)
    near_s_per_eval: float = 1.6e-9
    direct_s_per_pair: float = 1.4e-9
    fmm_s_per_point: tuple = ((1e-6, 1.65e-4), (1e-8, 2.35e-4), (1e-10, 2.5e-4))
    ewald: dict = field(default_factory=lambda: {
        "pair": 3.7e-9, "target": 2.3e-6, "own_pair": 1.5e-9, "nufft_point": 8.8e-10, "fft_point": 6.3e-10,
        "fft_growth": 0.3, "mode": 4.0e-9})
    source: str = "defaults"

    def constants(self):
        """The constants as a JSON-ready dict (the file's "constants")."""
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self) if f.name != "source"}


DEFAULTS = Calibration()
# how the defaults were measured (the development machine, 2 cores, one thread, process CPU time)
MEASURED = {
    "self_gemv_bytes_per_s": "2-5e10 measured, the lower end kept (benchmarks/iteration.py)",
    "forces_s": "p = 8 / 12 / 16: 1.3 / 2.4 / 4.8e-4 s per vesicle per iteration (benchmarks/cost_model.py)",
    "self_setup_s": "p = 6 / 8 / 12 / 16: 0.0019 / 0.0050 / 0.026 / 0.097 s per vesicle (benchmarks/cost_model.py)",
    "pc_setup_s": "p = 6 / 8 / 12 / 16: 0.007 / 0.012 / 0.057 / 0.26-0.36 s per vesicle (benchmarks/cost_model.py)",
    "near_s_per_eval": "near part at N = 64, p = 16, q = 32 (benchmarks/iteration.py --n 64)",
    "direct_s_per_pair": "two vesicles at p = 6 .. 16: 1.37-1.47 ns (benchmarks/cost_model.py)",
    "fmm_s_per_point": "N = 64 and 128 at p = 16, q = 32 (benchmarks/far_field.py --eps 1e-6 / 1e-8 / 1e-10)",
    "ewald": "free-space N = 32 / 64 / 128 and periodic N = 64 / 125 / 128 / 512, p = 16, tol 1e-6, "
             "at 1-4 cutoffs each (experiments/ewald_split.py); totals within 15 % at the chosen cutoff",
}


def _plain(v):
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (tuple, list)):
        return [_plain(x) for x in v]
    return v


def path():
    """The calibration file's path: $VESFLOW_CALIBRATION, else ~/.cache/vesflow/calibration.json."""
    return os.path.expanduser(os.environ.get(ENV) or DEFAULT_PATH)


def _positive(where, name, v):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise SettingsError(f"calibration file {where}: {name} = {v!r} must be a positive number")
    return float(v)


def from_dict(constants, source="defaults"):
    """A Calibration from a file's "constants" (missing names keep DEFAULTS; unknown names, non-positive
    values: SettingsError naming the file and the constant)."""
    known = {f.name for f in fields(Calibration)} - {"source"}
    unknown = sorted(set(constants) - known)
    if unknown:
        raise SettingsError(f"calibration file {source}: unknown constant(s) {', '.join(unknown)}; "
                            f"known: {', '.join(sorted(known))}")
    kw = {}
    for name, v in constants.items():
        if name in ("self_gemv_bytes_per_s", "near_s_per_eval", "direct_s_per_pair"):
            kw[name] = _positive(source, name, v)
        elif name in ("forces_s", "self_setup_s", "pc_setup_s"):
            if not isinstance(v, (list, tuple)) or len(v) != 2:
                raise SettingsError(f"calibration file {source}: {name} = {v!r} must be a pair [a, b]")
            kw[name] = tuple(_positive(source, f"{name}[{k}]", x) for k, x in enumerate(v))
        elif name == "fmm_s_per_point":
            if not isinstance(v, (list, tuple)) or not v or any(not isinstance(r, (list, tuple)) or len(r) != 2
                                                                for r in v):
                raise SettingsError(f"calibration file {source}: fmm_s_per_point = {v!r} must be a list of "
                                    "[eps, seconds per point]")
            kw[name] = tuple((_positive(source, "fmm_s_per_point eps", e), _positive(source, "fmm_s_per_point", t))
                             for e, t in v)
        else:   # ewald
            if not isinstance(v, dict) or sorted(v) != sorted(EWALD_KEYS):
                raise SettingsError(f"calibration file {source}: ewald must give exactly {', '.join(EWALD_KEYS)}")
            kw[name] = {k: _positive(source, f"ewald.{k}", v[k]) for k in EWALD_KEYS}
    return Calibration(source=source, **kw)


def load(file=None):
    """This machine's Calibration: the file (default path()) if it exists, else DEFAULTS.  A file
    that cannot be read or parsed is a SettingsError (one line, naming the file)."""
    p = os.path.expanduser(file) if file is not None else path()
    if not os.path.exists(p):
        if file is not None or os.environ.get(ENV):
            raise SettingsError(f"calibration file {p} does not exist (write it with benchmarks/calibrate.py, "
                                f"or unset {ENV})")
        return DEFAULTS
    try:
        with open(p, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError) as e:
        raise SettingsError(f"calibration file {p}: cannot read it ({e})") from None
    if not isinstance(data, dict) or data.get("version") != FILE_VERSION or not isinstance(data.get("constants"), dict):
        raise SettingsError(f"calibration file {p}: expected {{\"version\": {FILE_VERSION}, \"constants\": {{...}}}}")
    return from_dict(data["constants"], source=p)


def write(cal, file, **about):
    """Write a Calibration as a calibration file (``about``: how it was measured, e.g. the machine)."""
    p = os.path.expanduser(file)
    os.makedirs(os.path.dirname(os.path.abspath(p)), exist_ok=True)
    with open(p, "w", encoding="utf-8") as fh:
        json.dump({"version": FILE_VERSION, "constants": cal.constants(), **about}, fh, indent=1)
        fh.write("\n")
    return p

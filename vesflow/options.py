"""vesflow's own command-line options: a registry, typed reading, validation, help.

Options come through a *getter* ``getter(name, type, default) -> value or None`` (None: not
given), so the same code reads PETSc's options database (:func:`petsc_getter`), a plain dict
(:func:`dict_getter`, tests) or an argument list (:func:`argv_getter`).  Values may come typed
or as strings; they are converted and checked here, and every problem raises
:class:`vesflow.errors.OptionError` with one line ``-ves_p = 100: must be an integer in [2, 64]``.

    scene = apply_overrides(scene, getter)      # options that override scene keys
    opts = read_options(getter, scene)          # every other knob, defaults resolved
    opts.q_self, opts.adapt, opts["-ves_far"]

Nothing here imports petsc4py at module level.  The list is in docs/reference/options.md
(``markdown_text()``, ``python -m vesflow.options --markdown``) and ``help_text()`` (``vesflow run -help``).
"""
from __future__ import annotations

import difflib
import math
from collections.abc import Mapping
from dataclasses import dataclass

from .errors import OptionError, SceneError

__all__ = ["Option", "OPTIONS", "REGISTRY", "OptionValues", "apply_overrides", "read_options", "help_text",
           "dict_getter", "argv_getter", "argv_pairs", "petsc_getter", "check_unknown", "parse_value"]


@dataclass(frozen=True)
class Option:
    name: str                     # "-ves_q_self"
    type: type                    # int, float, str or bool
    default: object               # None: derived (see default_text) or "not set"
    help: str
    group: str
    scene_key: str | None = None  # the scene key this option overrides
    choices: tuple | None = None
    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None
    default_text: str | None = None
    alias_of: str | None = None   # another spelling of the same knob

    @property
    def key(self) -> str:
        """Attribute name in OptionValues: "-ves_q_self" -> "q_self", "-ts_max_steps" -> "ts_max_steps"."""
        k = self.name.lstrip("-")
        return k[4:] if k.startswith("ves_") else k

    @property
    def shown_default(self) -> str:
        if self.default_text is not None:
            return self.default_text
        if self.type is bool:
            return "on" if self.default else "off"
        return "none" if self.default is None else _show(self.default)

    @property
    def metavar(self) -> str:
        if self.choices:
            return "{" + ",".join(self.choices) + "}"
        return {int: "<int>", float: "<real>", str: "<string>", bool: "[on|off]"}[self.type]


def _show(v) -> str:
    if isinstance(v, bool):
        return "on" if v else "off"
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


_O = Option
REGISTRY: tuple[Option, ...] = (
    # -- scene overrides ---------------------------------------------------------------------
    _O("-ves_p", int, None, "spherical-harmonic degree p of every vesicle", "scene overrides",
       scene_key="discretization.p", ge=2, le=64, default_text="scene (16)"),
    _O("-ts_max_time", float, None, "time horizon T", "scene overrides",
       scene_key="time.horizon", gt=0, default_text="scene (10)"),
    _O("-ves_horizon", float, None, "same as -ts_max_time", "scene overrides",
       scene_key="time.horizon", gt=0, default_text="scene (10)", alias_of="-ts_max_time"),
    _O("-ts_dt", float, None, "first time step (adaptivity changes it)", "scene overrides",
       scene_key="time.dt", gt=0, default_text="scene (min(0.1, T/10))"),
    _O("-ves_repulsion_radius", float, None, "repulsion radius R_repul; 0 switches repulsion off",
       "scene overrides", scene_key="repulsion.radius", ge=0, default_text="scene (off)"),
    _O("-ves_output_every", float, None, "simulated time between saved frames", "scene overrides",
       scene_key="output.every", gt=0, default_text="scene (T/100)"),
    # -- quadrature and layer potentials -------------------------------------------------------
    _O("-ves_q_self", int, None, "upsampled degree q of the singular (self) quadrature, > p", "quadrature",
       ge=2, le=256, default_text="2p"),
    _O("-ves_q_near", int, None, "upsampled degree q of the near-singular rule, >= p", "quadrature",
       ge=2, le=256, default_text="2p"),
    _O("-ves_q_far", int, None, "same as -ves_q_near: the near-singular and far-field rules share one "
       "upsampled grid (paper 3.2.4)", "quadrature", ge=2, le=256, default_text="2p", alias_of="-ves_q_near"),
    _O("-ves_quad_tol", float, 0.0, "adapt the quadrature degrees to this error of the double-layer identity "
       "(paper 3.2.4): q_self (q_near) + 1 when the self (near or far) error is above it, - 1 when below "
       "tol / 10; 0 keeps q fixed", "quadrature", ge=0, lt=1),
    _O("-ves_q_max", int, None, "largest degree the quadrature adaptation may use", "quadrature",
       ge=2, le=256, default_text="4p"),
    _O("-ves_near_factor", float, 1.0, "near-zone width h_n = factor * sqrt(A_max / q_near)", "quadrature",
       gt=0, le=10),
    _O("-ves_wall_q", int, None, "upsampled degree q_w of a container's smooth and near-singular rules ([wall]; "
       "its near zone h_w = factor * sqrt(A_w / q_w), docs/explanation/walls.md)", "quadrature", ge=8, le=512,
       default_text="4 p_w"),
    _O("-ves_near_blend", float, 0.0, "blend the near-singular value into the smooth rule over "
       "h_n .. h_n (1 + blend) (C^2 weight) instead of switching at h_n: a velocity smooth in the positions, "
       "which high-order time steps need (docs/explanation/dynamics.md); 0 = switch", "quadrature", ge=0, le=1),
    _O("-ves_near_map_mb", float, 2048.0, "memory per rank (MB) for the near pairs' precomputed maps: each near "
       "pair within it gets its correction as a fixed linear map of the density, set up once per geometry "
       "(13.8 KB per pair and layer at p = 16; a GMRES iteration then costs ~1 us per pair instead of 9 q-grid "
       "sums, docs/explanation/performance.md); the others are evaluated every iteration; 0 = none",
       "quadrature", ge=0, le=1e7),
    _O("-ves_far", str, "auto", "far-field sum: auto = the faster of direct and fmm by the cost model "
       "measured on this machine (docs/explanation/far_field.md; fmm from about 140 vesicles at p = 16)", "quadrature",
       choices=("auto", "direct", "fmm", "ewald")),
    _O("-ves_ewald_own", str, "auto", "ewald far field, a vesicle's own sources: smooth = their Fourier share removed "
       "by per-vesicle operators built once per set-up (a cheaper GMRES iteration, a dearer set-up), subtract = "
       "in every iteration, auto = smooth when the cost model says the set-up pays over 15 applications per set-up "
       "(docs/explanation/far_field.md)", "quadrature", choices=("auto", "smooth", "subtract")),
    _O("-ves_ewald_grid", str, "replicated", "ewald far field, the Fourier grid: replicated = every rank holds "
       "the whole grid (NUFFT, the grid summed over the ranks), distributed = the fine grid in z-slabs over the "
       "ranks, grid memory per rank ~ grid / ranks plus the ghost planes of the rank's sources "
       "(docs/explanation/parallel.md, \"Distributed Ewald grid\")", "quadrature",
       choices=("replicated", "distributed")),
    _O("-ves_far_tol", float, 1e-8, "requested relative accuracy of the fmm / ewald far-field sum",
       "quadrature", gt=0, lt=1),
    _O("-ves_pc_lag", int, 50, "rebuild the block preconditioner from the current shapes after at most this "
       "many solves (sooner when the GMRES iterations grow by half, docs/explanation/dynamics.md; 1 = every step)",
       "solver", ge=1, le=100000),
    _O("-ves_self_precision", str, "double", "storage and product of the singular self operators: single "
       "(float32) halves their memory, the largest per-vesicle array (docs/explanation/parallel.md)", "solver",
       choices=("double", "single")),
    _O("-ves_pc_precision", str, "double", "block preconditioner's parts and LU factors: single (float32) "
       "halves their memory; the KSP is then fgmres unless -ksp_type is given (docs/explanation/parallel.md)", "solver",
       choices=("double", "single")),
    _O("-ves_pc_factors", int, 3, "sets of LU factors the block preconditioner keeps, one per time-step size "
       "(sdc's substeps and velocity solves take 3; fewer: each costs 10 MB per vesicle at p = 16 in double, a new "
       "one is factored when no kept one matches, docs/explanation/parallel.md)", "solver", ge=1, le=3),
    _O("-ves_pc_parts", str, "keep", "block preconditioner's parts (the blocks before their LU at a given dt): keep "
       "them, or drop them once factored (a dt no kept factor matches then rebuilds the blocks from the current "
       "shapes; docs/explanation/parallel.md)", "solver", choices=("keep", "drop")),
    _O("-ves_setup_cache", str, "start", "layer potentials (self operators, near pairs) kept across the solves of an sdc "
       "step: start = the step's start's, which every sweep reuses, and the current ones; current = the current ones "
       "only (one set less in memory, 2 more set-ups per step; docs/explanation/parallel.md)", "solver",
       choices=("start", "current")),
    _O("-ves_memory_limit", float, None, "memory the run may use, GiB: where the defaults' modelled peak would "
       "not fit, vesflow run and check choose memory options that do (said in one line) or refuse naming what "
       "would fit (docs/explanation/parallel.md)", "solver", gt=0, default_text="MemAvailable of /proc/meminfo"),
    _O("-ves_blas_threads", int, 1, "BLAS threads (numpy's OpenBLAS); the OpenMP kernels use OMP_NUM_THREADS "
       "(vesflow.threads, docs/explanation/performance.md)", "solver", ge=1, le=1024),
    _O("-ves_coupling", str, "implicit", "inter-vesicle interactions in the solve (implicit) or "
       "lagged to the right-hand side (explicit: cheaper, less stable)", "solver",
       choices=("implicit", "explicit")),
    # -- time stepping ---------------------------------------------------------------------------
    _O("-ts_type", str, None, "time integrator: euler (the first-order semi-implicit step, paper 3.6) or "
       "sdc (spectral deferred correction on it, order min(sweeps + 1, 2 nodes - 2), vesflow/stepping/sdc.py; cheaper "
       "than euler at the same error but the loosest, docs/explanation/accuracy_cost.md)",
       "time stepping", choices=("euler", "sdc"), default_text="sdc (euler with -ves_coupling explicit)"),
    _O("-ts_sdc_nodes", int, 3, "nodes of an sdc step with its start (nodes - 1 substeps)", "time stepping",
       ge=2, le=9),
    _O("-ts_sdc_quadrature", str, "radau", "nodes of an sdc step: lobatto (Gauss-Lobatto, order 2 nodes - 2) "
       "or radau (the step's start and Radau IIA nodes, order 2 nodes - 3, L-stable: stiff modes damped)",
       "time stepping", choices=("lobatto", "radau")),
    _O("-ts_sdc_sweeps", int, 2, "correction sweeps of an sdc step (each one order more)", "time stepping",
       ge=1, le=20),
    _O("-ves_adapt", str, None, "adaptive time step: none (fixed dt), doubling (one step vs two "
       "half steps), invariants (relative change of area and volume), sweeps (difference of the last "
       "two sdc sweeps), contraction (error of the kept sdc state from its sweeps' contraction; "
       "misses the stiff collocation error, docs/explanation/dynamics.md)", "time stepping",
       choices=("none", "doubling", "invariants", "sweeps", "contraction"), default_text="doubling (euler), sweeps (sdc)"),
    _O("-ves_adapt_tol", float, 1e-2, "accepted error per unit simulated time, E / T", "time stepping", gt=0),
    _O("-ves_adapt_beta", float, None, "safety factor beta of the step-size update (sdc: its d_K varies by "
       "+-40% from step to step, and with 0.9 a quarter of the steps were rejected, docs/explanation/accuracy_cost.md)",
       "time stepping", default_text="0.9 (euler), 0.75 (sdc)",
       gt=0, le=1),
    _O("-ves_dt_min", float, 1e-6, "smallest time step (also bounds the first step); below it the run stops (exit status 3)",
       "time stepping", gt=0),
    _O("-ves_dt_max", float, None, "largest time step (also bounds the first step)", "time stepping", gt=0, default_text="none"),
    _O("-ves_max_rejects", int, 20, "consecutive rejected steps before the run stops (exit status 3)",
       "time stepping", ge=1),
    _O("-ves_collision", bool, True, "reject a step whose surfaces touch or cross", "time stepping"),
    _O("-ves_contact", bool, True, "a touching step that starts in contact (gap below 1% of the grid spacing) "
       "moves the touching vesicles apart rigidly instead of being rejected: the lubrication layer is not "
       "resolved there (vesflow/contact.py, docs/explanation/contacts.md)", "time stepping"),
    _O("-ts_max_steps", int, None, "stop after this many accepted steps", "time stepping", ge=0,
       default_text="none"),
    _O("-ts_monitor", bool, False, "print one line per attempted step", "time stepping"),
    # -- corrections -------------------------------------------------------------------------------
    _O("-ves_correct", str, "area_volume", "restore each vesicle's area and volume after a step",
       "corrections", choices=("area_volume", "none")),
    _O("-ves_correct_tol", float, 1e-10, "relative area / volume error left by the correction",
       "corrections", gt=0, lt=1),
    _O("-ves_correct_max_its", int, 5, "Newton iterations of the correction", "corrections", ge=1, le=100),
    _O("-ves_keep_centroid", bool, True, "the post-step (reparameterization and area / volume correction) "
       "keeps each vesicle's centroid: its net translation is removed (docs/explanation/dynamics.md)", "corrections"),
    _O("-ves_reparam", bool, True, "reparameterize surfaces (tangential moves) after each step", "corrections"),
    _O("-ves_reparam_dtau_max", float, 1e-3, "largest pseudo-time step of reparameterization",
       "corrections", gt=0),
    _O("-ves_reparam_tol", float, 1e-5, "reparameterization stops when the pseudo-time step falls below this",
       "corrections", gt=0),
    _O("-ves_reparam_max_its", int, 20, "reparameterization iterations per time step (the least; -ves_reparam_rate)", "corrections",
       ge=1, le=10000),
    _O("-ves_reparam_rate", float, None, "reparameterization iterations per unit simulated time: a step of dt "
       "takes up to max(-ves_reparam_max_its, rate dt) (the grid distorts per unit time, not per step; euler's "
       "short steps get that from -ves_reparam_max_its, docs/explanation/dynamics.md)",
       "corrections", ge=0, default_text="1000 (sdc), 0 (euler)"),
    _O("-ves_reparam_attenuation", str, "n2", "weights a_n of the mesh-quality energy E = sum a_n^2 |Y_nm|^2 "
       "(paper Fig. 4): n2 = n^2, n, n16 = n^16 (scaled), step = H(n - 2p/3)", "corrections",
       choices=("n2", "n", "n16", "step")),
    # -- output ----------------------------------------------------------------------------------
    _O("-ves_checkpoint_every", float, None, "simulated time between restart checkpoints", "output",
       gt=0, default_text="output.every"),
    _O("-ves_progress", str, "auto", "progress line: auto = only on a terminal", "output",
       choices=("auto", "on", "off")),
    _O("-ves_traceback", bool, False, "an unexpected error (a PETSc error, a bug) prints Python's full "
       "traceback after its one-line message (for debugging)", "output"),
)
del _O
OPTIONS: dict[str, Option] = {o.name: o for o in REGISTRY}
GROUPS = ("scene overrides", "quadrature", "solver", "time stepping", "corrections", "output")

_TRUE = ("1", "true", "yes", "on", "")
_FALSE = ("0", "false", "no", "off")


def _fail(opt: Option, raw, msg: str):
    err = OptionError(f"{opt.name} = {_fmt_raw(raw)}: {msg}")
    err.key = opt.name
    raise err


def _fmt_raw(raw) -> str:
    if isinstance(raw, bool):
        return "on" if raw else "off"
    s = (raw if raw.strip() else repr(raw)) if isinstance(raw, str) else _show(raw)
    return s if len(s) <= 60 else s[:57] + "..."


def _range_text(o: Option) -> str:
    lo = f"({_show(o.gt)}" if o.gt is not None else (f"[{_show(o.ge)}" if o.ge is not None else None)
    hi = f"{_show(o.lt)})" if o.lt is not None else (f"{_show(o.le)}]" if o.le is not None else None)
    what = "an integer" if o.type is int else "a number"
    if lo and hi:
        return f"must be {what} in {lo}, {hi}"
    if lo:
        return f"must be {what} {'>' if o.gt is not None else '>='} {_show(o.gt if o.gt is not None else o.ge)}"
    if hi:
        return f"must be {what} {'<' if o.lt is not None else '<='} {_show(o.lt if o.lt is not None else o.le)}"
    return f"must be {what}"


def parse_value(opt: Option | str, raw):
    """Convert and check one option value (typed or string); raises OptionError."""
    o = OPTIONS[opt] if isinstance(opt, str) else opt
    if o.type is bool:
        if isinstance(raw, bool):
            return raw
        if isinstance(raw, str) and raw.strip().lower() in _TRUE + _FALSE:
            return raw.strip().lower() in _TRUE
        if isinstance(raw, int) and raw in (0, 1):
            return bool(raw)
        _fail(o, raw, "expected on or off (true/false, yes/no, 1/0)")
    if o.type is str:
        if not isinstance(raw, str):
            _fail(o, raw, f"expected one of {', '.join(o.choices)}" if o.choices else "expected a string")
        v = raw.strip()
        if o.choices and v not in o.choices:
            sugg = difflib.get_close_matches(v, o.choices, n=1, cutoff=0.5)
            _fail(o, raw, f"must be one of {', '.join(o.choices)}" + (f"; did you mean {sugg[0]}?" if sugg else ""))
        return v
    if isinstance(raw, bool):
        _fail(o, raw, _range_text(o))
    v = _number(o, raw)
    if o.type is float and not math.isfinite(v):
        _fail(o, raw, "must be a finite number")
    bad = ((o.gt is not None and not v > o.gt) or (o.ge is not None and not v >= o.ge)
           or (o.lt is not None and not v < o.lt) or (o.le is not None and not v <= o.le))
    if bad:
        _fail(o, raw, _range_text(o))
    return v


def _number(o: Option, raw):
    """raw (a number or its text) as o.type (int: an integral float is accepted), or _fail."""
    if o.type is int and isinstance(raw, float) and raw.is_integer():
        raw = int(raw)
    numeric = (int,) if o.type is int else (int, float)
    try:
        if isinstance(raw, numeric):
            return o.type(raw)
        if isinstance(raw, str):
            return o.type(raw.strip())
    except ValueError:
        pass
    _fail(o, raw, _range_text(o))


def _get(getter, o: Option):
    raw = getter(o.name, o.type, o.default)
    return None if raw is None else parse_value(o, raw)


# ----------------------------------------------------------------------------------------
# Scene overrides
# ----------------------------------------------------------------------------------------
def apply_overrides(scene, getter):
    """A new Scene with the values of the options that override scene keys (-ves_p,
    -ts_max_time / -ves_horizon, -ts_dt, -ves_repulsion_radius, -ves_output_every).
    Defaults derived from the horizon (time.dt, output.every) follow a new horizon unless
    they were given in the scene."""
    vals = {o.name: _get(getter, o) for o in REGISTRY if o.scene_key is not None}
    h1, h2 = vals.pop("-ts_max_time"), vals.pop("-ves_horizon")
    if h1 is not None and h2 is not None and h1 != h2:
        _fail(OPTIONS["-ves_horizon"], h2, f"contradicts -ts_max_time = {_show(h1)} (give one of them)")
    horizon = h1 if h1 is not None else h2
    changes = {}
    if horizon is not None:
        changes["time.horizon"] = horizon
    for name, v in vals.items():
        if v is not None:
            changes[OPTIONS[name].scene_key] = v
    if not changes:
        return scene
    new = scene.replace(**changes)
    t = new.time
    if t.dt > t.horizon:
        if "time.dt" in changes:
            _fail(OPTIONS["-ts_dt"], changes["time.dt"], f"larger than the time horizon {_show(t.horizon)}")
        name = "-ts_max_time" if h1 is not None else "-ves_horizon"
        _fail(OPTIONS[name], horizon, f"smaller than the first time step time.dt = {_show(t.dt)} "
                                      "(give -ts_dt too)")
    return new


# ----------------------------------------------------------------------------------------
# All other knobs
# ----------------------------------------------------------------------------------------
class OptionValues(Mapping):
    """Resolved option values (immutable): by key (``opts.q_self``, ``opts["q_self"]``) or by
    option name (``opts["-ves_q_self"]``).  ``given`` holds the names set by the user."""

    def __init__(self, values: dict, given: frozenset):
        object.__setattr__(self, "_values", dict(values))
        object.__setattr__(self, "given", frozenset(given))

    def __getitem__(self, k):
        if k in OPTIONS:
            k = OPTIONS[k].key
        return self._values[k]

    def __iter__(self):
        return iter(self._values)

    def __len__(self):
        return len(self._values)

    def __getattr__(self, k):
        try:
            return self._values[k]
        except KeyError:
            raise AttributeError(k) from None

    def __setattr__(self, k, v):
        raise AttributeError("OptionValues is immutable")

    def replaced(self, changes: dict) -> "OptionValues":
        """A copy with the values of `changes` (keys) in place of these; `given` unchanged."""
        vals = dict(self._values)
        vals.update(changes)
        return OptionValues(vals, self.given)

    def as_argv(self) -> list[str]:
        """The options in force as an argument list (for the output file's record)."""
        out = []
        for o in REGISTRY:
            if o.scene_key is None and o.key in self._values and self._values[o.key] is not None:
                out += [o.name, _show(self._values[o.key])]
        return out

    def __repr__(self):
        return "OptionValues(" + ", ".join(f"{k}={v!r}" for k, v in self._values.items()) + ")"


def read_options(getter, scene=None) -> OptionValues:
    """Every option that is not a scene override, checked, with derived defaults resolved
    against the scene (q_self = q_near = q_far = 2p, q_max = 4p, checkpoint_every = output.every)."""
    vals, given = {}, set()
    for o in REGISTRY:
        if o.scene_key is not None:
            continue
        v = _get(getter, o)
        if v is None:
            v = o.default
        else:
            given.add(o.name)
        vals[o.key] = v
    if scene is not None:
        p = scene.discretization.p
        if vals["q_far"] is not None:
            if vals["q_near"] is not None and vals["q_near"] != vals["q_far"]:
                _fail(OPTIONS["-ves_q_far"], vals["q_far"], f"contradicts -ves_q_near = {vals['q_near']} "
                      "(one grid serves both rules; give one of them)")
            vals["q_near"] = vals["q_far"]
        for key, mult in (("q_self", 2), ("q_near", 2), ("q_max", 4)):
            if vals[key] is None:
                vals[key] = mult * p
            elif vals[key] < p + (key == "q_self"):
                _fail(OPTIONS[f"-ves_{key}"], vals[key], f"must be {'>' if key == 'q_self' else '>='} p = {p}")
        vals["q_far"] = vals["q_near"]
        for key in ("q_self", "q_near"):
            if vals["quad_tol"] > 0 and vals[key] > vals["q_max"]:
                _fail(OPTIONS[f"-ves_{key}"], vals[key], f"must be <= -ves_q_max = {vals['q_max']}")
        if vals["checkpoint_every"] is None:
            vals["checkpoint_every"] = scene.output.every
    if vals["ts_type"] is None:        # sdc integrates the velocity field: lagged coupling is not it
        vals["ts_type"] = "euler" if vals["coupling"] == "explicit" else "sdc"
    if vals["adapt"] is None:
        vals["adapt"] = "sweeps" if vals["ts_type"] == "sdc" else "doubling"
    elif vals["adapt"] in ("sweeps", "contraction") and vals["ts_type"] != "sdc":
        _fail(OPTIONS["-ves_adapt"], vals["adapt"], f"needs -ts_type sdc (-ts_type is {vals['ts_type']})")
    if vals["adapt_beta"] is None:
        vals["adapt_beta"] = 0.75 if vals["ts_type"] == "sdc" else 0.9
    if vals["reparam_rate"] is None:
        vals["reparam_rate"] = 1000.0 if vals["ts_type"] == "sdc" else 0.0
    if vals["ts_type"] == "sdc" and vals["coupling"] != "implicit":
        _fail(OPTIONS["-ts_type"], "sdc", "needs -ves_coupling implicit (the quadrature integrates the "
              "velocity field; lagged coupling terms are not it)")
    if vals["dt_max"] is not None and vals["dt_min"] >= vals["dt_max"]:
        _fail(OPTIONS["-ves_dt_min"], vals["dt_min"], f"must be < -ves_dt_max = {_show(vals['dt_max'])}")
    if vals["reparam_tol"] >= vals["reparam_dtau_max"]:
        _fail(OPTIONS["-ves_reparam_tol"], vals["reparam_tol"],
              f"must be < -ves_reparam_dtau_max = {_show(vals['reparam_dtau_max'])}")
    return OptionValues(vals, frozenset(given))


def check_unknown(names) -> None:
    """Raise OptionError for a given name that looks like a vesflow option but is not one
    (``-ves_qself`` -> did you mean -ves_q_self?).  Names with or without the leading dash."""
    known = [o.name for o in REGISTRY]
    for n in names:
        name = "-" + str(n).lstrip("-")
        if name.startswith("-ves_") and name not in OPTIONS:
            sugg = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
            err = OptionError(f"{name}: unknown vesflow option; " + (f"did you mean {sugg[0]}?" if sugg
                              else "see vesflow run -help"))
            err.key = name
            raise err


# ----------------------------------------------------------------------------------------
# Getters
# ----------------------------------------------------------------------------------------
def dict_getter(d: Mapping):
    """Getter over a dict keyed by option name, with or without the leading dash."""
    norm = {"-" + str(k).lstrip("-"): v for k, v in d.items()}
    return lambda name, type_, default: norm.get(name)


def take_valued(args, names, what="a value"):
    """The arguments of a command line split into ([(name, value)] for every name of `names`
    with the argument after it, in order; the other arguments); SceneError "NAME needs WHAT"
    when a name ends the line."""
    pairs, others, k = [], [], 0
    while k < len(args):
        a = args[k]
        if a in names:
            if k + 1 >= len(args):
                raise SceneError(f"{a} needs {what}")
            pairs.append((a, args[k + 1]))
            k += 2
        else:
            others.append(a)
            k += 1
    return pairs, others


def argv_pairs(argv):
    """The options of a PETSc-style argument list ``[-name value | -flag ...]`` in order, as
    (index of the name in argv, "-name", value or None for a flag).  A name followed by another
    option name (or nothing) is a flag; a negative number is a value."""
    args = list(argv)
    out, k = [], 0
    while k < len(args):
        a = args[k]
        if a.startswith("-") and not _is_number(a):
            name = "-" + a.lstrip("-")
            if k + 1 < len(args) and not (args[k + 1].startswith("-") and not _is_number(args[k + 1])):
                out.append((k, name, args[k + 1]))
                k += 2
                continue
            out.append((k, name, None))
        k += 1
    return out


def argv_getter(argv):
    """Getter over a PETSc-style argument list ``[-name value | -flag ...]`` without PETSc
    (see argv_pairs; a flag has the value "")."""
    vals = {name: ("" if value is None else value) for _, name, value in argv_pairs(argv)}

    def get(name, type_, default):
        if name not in vals:
            return None
        v = vals[name]
        if v == "" and type_ is not bool:
            o = OPTIONS.get(name)
            if o is not None:
                _fail(o, v, "needs a value")
        return v
    return get


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def petsc_getter(opts=None):
    """Getter over PETSc's options database (petsc4py imported here, not at module level).
    Values are read as strings and checked by parse_value."""
    if opts is None:
        from petsc4py import PETSc
        opts = PETSc.Options()

    def get(name, type_, default):
        key = name.lstrip("-")
        if not opts.hasName(key):
            return None
        v = opts.getString(key, "")
        return "" if v is None else v
    return get


# ----------------------------------------------------------------------------------------
# Help
# ----------------------------------------------------------------------------------------
def help_text() -> str:
    """Every vesflow option with its default, grouped (for `vesflow run -help`)."""
    lines = ["vesflow options (a command-line option overrides the scene's value of the same knob;",
             "PETSc's own options such as -ksp_rtol, -ksp_monitor, -pc_type, -log_view work as usual):"]
    width = max(len(o.name) + 1 + len(o.metavar) for o in REGISTRY) + 2
    for g in GROUPS:
        lines.append("")
        lines.append(f"{g}:")
        for o in REGISTRY:
            if o.group != g:
                continue
            rng = ""
            if o.type in (int, float) and any(x is not None for x in (o.gt, o.ge, o.lt, o.le)):
                rng = "; " + _range_text(o).replace("must be an integer ", "").replace("must be a number ", "")
            extra = f"; overrides {o.scene_key}" if o.scene_key else ""
            lines.append(f"  {(o.name + ' ' + o.metavar).ljust(width)}default: {o.shown_default}")
            lines.append(f"      {o.help}{extra}{rng}")
    return "\n".join(lines)


def markdown_text() -> str:
    """docs/reference/options.md: the registry as Markdown tables, one per group
    (``python -m vesflow.options --markdown > docs/reference/options.md``)."""
    def cell(s: str) -> str:
        return s.replace("|", "\\|")

    lines = ["# Options", "",
             "Every vesflow option, generated from the option registry (`vesflow/options.py`) by",
             "`python -m vesflow.options --markdown > docs/reference/options.md`; `vesflow run -help`",
             "prints the same list.  A command-line option overrides the scene's value of the same knob",
             "and the options files before it; PETSc's own options (`-ksp_rtol`, `-ksp_monitor`,",
             "`-pc_type`, `-log_view`, ...) work as usual.  A value outside its range, or an unknown",
             "`-ves_` option, stops the run before any work with a one-line message (exit status 2)."]
    for g in GROUPS:
        lines += ["", f"## {g[0].upper() + g[1:]}", "",
                  "| option | value | default | what it sets |", "|---|---|---|---|"]
        for o in REGISTRY:
            if o.group != g:
                continue
            what = o.help
            if o.type in (int, float) and any(x is not None for x in (o.gt, o.ge, o.lt, o.le)):
                what += "; " + _range_text(o)
            if o.scene_key:
                what += f"; overrides the scene key `{o.scene_key}`"
            if o.alias_of:
                what += f"; another spelling of `{o.alias_of}`"
            lines.append(f"| `{o.name}` | `{cell(o.metavar)}` | {cell(o.shown_default)} | {cell(what)} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    import sys
    if sys.argv[1:] != ["--markdown"]:
        sys.exit("usage: python -m vesflow.options --markdown   (the options reference, docs/reference/options.md)")
    sys.stdout.write(markdown_text())

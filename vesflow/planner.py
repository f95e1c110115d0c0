"""Ask for an accuracy, get the cheapest settings: `vesflow plan SCENE.toml --error E [--budget S]`.

The error of a run at the horizon T (the accuracy-cost study's measure: max over vesicles of the
centroid's distance from a converged solution's, over the vesicle's length; docs/explanation/accuracy_cost.md)
is modelled as the sum of a spatial and a time part (docs/explanation/planner.md):

    e(p, scheme, E/T) = (T / T_fit) [f_s e_s(p) + f_t e_t(scheme, E/T)] + e_far(tol_far)
    e_s(p) = A_s (r_s^p - r_s^p_ref)            spatial, against a p_ref = 16 solution
    e_t(scheme, E/T) = A_t (E/T / 1e-2)^a_t     time, per scheme (euler with step doubling, sdc)

and its time (CPU seconds of one thread) as the solves it takes times what one solve costs:

    solves = max(s T (E/T / 1e-2)^-b, n_step n_min)   per scheme; n_min: the fewest steps (fewest_steps)
    time = solves [alpha k t_solve(p) + beta c N]   t_solve: vesflow.costs (the model of `vesflow check`)

The constants (FIT) are fitted by vesflow.plan_fit to the study's cases; f_s, f_t and a factor on
the time are 1 unless pilot runs (`--pilot`) measured them on the scene itself.  The search
enumerates p, the scheme and E/T on a grid, takes the far-field tolerance and precision that
cost least without adding more than a tenth of E, and returns the cheapest setting that reaches
E (or, with a budget, the smallest error within it) and the runner-up.
"""
from __future__ import annotations

import math
import shlex
from dataclasses import asdict, dataclass, field, replace

from . import costs, options as optmod
from .errors import SceneError

# Fitted by `python -m vesflow.plan_fit` (vesflow/plan_fit.py: fit_from_study) to the 15 cases of
# docs/study (runs/accuracy_cost.toml: two oblate vesicles v = 0.85 in shear, T = 7,
# frames at 0 and T, one thread) against its reference, sdc at p = 16, E/T = 1e-4: e_t from the
# p = 16 cases of each scheme (no spatial error against a p = 16 reference), e_s from the rest
# after their e_t, the solves by least squares in log(E/T), k and c by least squares on the CPU
# per solve (relative residuals) with vesflow.costs' t_solve at each p.
FIT = {
    "source": "docs/study (runs/accuracy_cost.toml; reference sdc p = 16, E/T = 0.0001)",
    "horizon": 7, "n_vesicles": 2, "p_ref": 16,
    "spatial": {"A": 0.01686254917, "r": 0.795},
    "time": {"euler": {"A": 0.001683757743, "a": 1.046177139}, "sdc": {"A": 0.0001174191222, "a": 1.576596524}},
    "solves": {"euler": {"s": 45.30490584, "b": 0.8807679567}, "sdc": {"s": 41.07908993, "b": 0.2137252664}},
    "cost": {"euler": {"k": 1.46695367, "c": 0.02385705833}, "sdc": {"k": 1.269936685, "c": 0.01234524391}},
}

SCHEMES = ("euler", "sdc")
P_CHOICES = tuple(range(8, 17))                    # the study's degrees: outside them the spatial model is not fitted
TOL_GRID = tuple(float(f"{1e-3 * 2 ** (k / 2):.3g}") for k in range(0, 13))   # E/T 1e-3 ... 6.4e-2, sqrt(2) apart
FAR_TOLS = (1e-4, 1e-5, 1e-6, 1e-7, 1e-8)          # -ves_far_tol (fmm / ewald only)
SOLVES_PER_STEP = {"euler": 3, "sdc": 10}         # step doubling; 3 Radau nodes x 2 sweeps (vesflow.sdc)
SINGLE_MIN_ERROR = 1e-6                            # float32 self operators: 1.8e-10 at T = 1 (docs/explanation/parallel.md)


@dataclass(frozen=True)
class Setting:
    """One candidate run: what `vesflow run` needs on its command line."""

    scheme: str
    p: int
    tol: float                      # -ves_adapt_tol = E / T
    q_self: int
    q_near: int
    R: float = 0.0                  # repulsion radius (0: off)
    far_tol: float | None = None    # None: direct far-field sum (no tolerance)
    precision: str = "double"       # -ves_self_precision

    def options(self):
        """The -ves_ / -ts_ options of this setting (dict, option name -> value)."""
        o = {"-ts_type": self.scheme, "-ves_p": self.p, "-ves_adapt_tol": float(f"{self.tol:.3g}"),
             "-ves_q_self": self.q_self, "-ves_q_near": self.q_near, "-ves_repulsion_radius": self.R,
             "-ves_self_precision": self.precision}
        if self.far_tol is not None:
            o["-ves_far_tol"] = self.far_tol
        return o

    def argv(self):
        return [str(x) for k, v in self.options().items() for x in (k, f"{v:g}" if isinstance(v, float) else v)]

    def describe(self):
        far = "direct far field" if self.far_tol is None else f"far tol {self.far_tol:g}"
        return (f"{self.scheme}, p = {self.p}, E/T = {self.tol:.3g}, q_self = {self.q_self}, q_near = {self.q_near}, "
                + (f"repulsion {self.R:g}" if self.R > 0 else "repulsion off") + f", {far}, {self.precision}")


@dataclass(frozen=True)
class Prediction:
    setting: Setting
    error: float
    e_space: float
    e_time: float
    e_far: float
    solves: float
    seconds: float

    def line(self):
        return (f"{self.setting.describe()}: error {self.error:.2g} (spatial {self.e_space:.2g}, time "
                f"{self.e_time:.2g}), {self.seconds:.3g} s CPU ({self.solves:.0f} solves)")


@dataclass
class Model:
    """The fitted constants (FIT) and the scene's calibration factors (1 unless pilots ran)."""

    fit: dict
    f_space: float = 1.0
    f_time: dict = field(default_factory=lambda: {"euler": 1.0, "sdc": 1.0})
    f_solves: dict = field(default_factory=lambda: {"euler": 1.0, "sdc": 1.0})
    f_cost: dict = field(default_factory=lambda: {"euler": 1.0, "sdc": 1.0})
    # the scene's split of a solve's cost (pilots): alpha k t_solve + beta c N
    split: tuple = (1.0, 1.0)
    # per scheme, the smallest E/T at which the pilot took exactly the fewest steps (None: unknown)
    floor_tol: dict = field(default_factory=lambda: {"euler": None, "sdc": None})
    pilot: str = ""                 # what calibrated the factors ("": the study's constants)

    def e_space(self, p, horizon):
        s, pref = self.fit["spatial"], self.fit["p_ref"]
        raw = s["A"] * max(s["r"] ** p - s["r"] ** pref, 0.0) if p < pref else 0.0
        return self.f_space * raw * horizon / self.fit["horizon"]

    def reference_error(self, horizon):
        """The p_ref solution's own spatial error by the same fit (A_s r_s^p_ref): not in e_s."""
        s = self.fit["spatial"]
        return self.f_space * s["A"] * s["r"] ** self.fit["p_ref"] * horizon / self.fit["horizon"]

    def e_time(self, scheme, tol, horizon):
        t = self.fit["time"][scheme]
        return self.f_time[scheme] * t["A"] * (tol / 1e-2) ** t["a"] * horizon / self.fit["horizon"]

    def solves(self, scheme, tol, horizon, dt0=None):
        """The fitted count, and at least the solves of the fewest steps that reach the horizon
        (dt0: the scene's first step; the step grows at most 2x per accepted step).  Where a
        pilot over the whole horizon took the fewest steps, their solves n_min from E/T =
        floor_tol up and n_min (E/T / floor_tol)^-b below it."""
        s = self.fit["solves"][scheme]
        floor = SOLVES_PER_STEP[scheme] * fewest_steps(horizon, dt0) if dt0 else 0
        ft = self.floor_tol.get(scheme)
        if ft is not None and floor:
            return float(floor) if tol >= ft else floor * (tol / ft) ** (-s["b"])
        n = self.f_solves[scheme] * s["s"] * horizon * (tol / 1e-2) ** (-s["b"])
        return max(n, floor) if dt0 else n

    def seconds_per_solve(self, scheme, t_solve, n_vesicles):
        """f_c (alpha k t_solve + beta c N): k, c the study's (per scheme), alpha, beta the
        scene's split (1, 1 without pilots)."""
        c, (al, be) = self.fit["cost"][scheme], self.split
        return self.f_cost[scheme] * (al * c["k"] * t_solve + be * c["c"] * n_vesicles)


def fewest_steps(horizon, dt0):
    """Steps dt0, 2 dt0, 4 dt0, ... (the last one landing on the horizon) that cover it."""
    n, t, dt = 0, 0.0, dt0
    while t < horizon * (1 - 1e-12):
        t, dt, n = t + dt, 2 * dt, n + 1
    return n


def t_solve(scene, setting):
    """Seconds of one implicit solve by vesflow.costs: its set-up and the assumed GMRES
    iterations (costs.ITERATIONS_PER_SOLVE) of the scene at the setting's p, q, far field."""
    sc = optmod.apply_overrides(scene, optmod.dict_getter({"-ves_p": setting.p}))
    given = {"-ves_q_self": setting.q_self, "-ves_q_near": setting.q_near, "-ves_self_precision": setting.precision}
    if setting.far_tol is not None:
        given["-ves_far_tol"] = setting.far_tol
    est = costs.estimate(sc, optmod.read_options(optmod.dict_getter(given), sc))
    return est.t_setup + est.iterations_per_solve * est.t_iteration, est.far_backend


class Planner:
    """Predictions and the search for one scene (cost-model figures cached per p)."""

    def __init__(self, scene, model=None, fixed=None):
        self.scene, self.model = scene, model or Model(FIT)
        self.fixed = dict(fixed or {})        # "p", "scheme", "tol", "R" given by the user
        self._t = {}

    def _solve_cost(self, setting):
        key = (setting.p, setting.q_self, setting.q_near, setting.far_tol, setting.precision)
        if key not in self._t:
            self._t[key] = t_solve(self.scene, setting)
        return self._t[key]

    def predict(self, setting):
        T, m = self.scene.time.horizon, self.model
        es, et = m.e_space(setting.p, T), m.e_time(setting.scheme, setting.tol, T)
        ef = 0.0 if setting.far_tol is None else setting.far_tol * T
        n = m.solves(setting.scheme, setting.tol, T, self.scene.time.dt)
        t, _ = self._solve_cost(setting)
        sec = n * m.seconds_per_solve(setting.scheme, t, self.scene.n_vesicles)
        return Prediction(setting, es + et + ef, es, et, ef, n, sec)

    def _far_and_precision(self, base, target):
        """The far-field tolerances and self-operator precision of p's settings: the loosest
        tolerance that adds at most a tenth of the target error (target None, a budget: every
        tolerance, each a candidate), float32 where allowed and 5 % cheaper by the cost model."""
        _, backend = self._solve_cost(base)
        T = self.scene.time.horizon
        if backend in ("none", "direct"):
            far = [None]
        else:
            far = [f for f in FAR_TOLS if target is None or f * T <= 0.1 * target] or [FAR_TOLS[-1]]
            far = far if target is None else far[:1]
        out = []
        for f in far:
            s = replace(base, far_tol=f)
            if target is None or target >= SINGLE_MIN_ERROR:
                single = replace(s, precision="single")
                if self._solve_cost(single)[0] < 0.95 * self._solve_cost(s)[0]:
                    s = single
            out.append(s)
        return out

    def candidates(self, target=None):
        fx = self.fixed
        R = fx.get("R", self.scene.repulsion.radius if self.scene.repulsion is not None else 0.0)
        out = []
        for p in ([fx["p"]] if "p" in fx else P_CHOICES):
            for base in self._far_and_precision(Setting("sdc", p, 1e-2, 2 * p, 2 * p, R), target):
                for scheme in ([fx["scheme"]] if "scheme" in fx else SCHEMES):
                    for tol in ([fx["tol"]] if "tol" in fx else TOL_GRID):
                        out.append(self.predict(replace(base, scheme=scheme, tol=tol)))
        return out

    def plan(self, error=None, budget=None):
        """(best, runner-up) Predictions: the cheapest reaching `error` (within `budget` if
        given), or the smallest error within `budget`.  SceneError (one line) if none can."""
        if error is None and budget is None:
            raise SceneError("vesflow plan: give --error E (and optionally --budget SECONDS)")
        cands = self.candidates(error)
        if error is not None:
            ok = [c for c in cands if c.error <= error and (budget is None or c.seconds <= budget)]
            key = lambda c: (c.seconds, c.error)
        else:
            ok = [c for c in cands if c.seconds <= budget]
            key = lambda c: (c.error, c.seconds)
        if not ok:
            raise SceneError(self._unreachable(cands, error, budget))
        ok.sort(key=key)
        best = ok[0]
        other = [c for c in ok[1:] if (c.setting.scheme, c.setting.p) != (best.setting.scheme, best.setting.p)]
        return best, (other[0] if other else (ok[1] if len(ok) > 1 else None))

    def _unreachable(self, cands, error, budget):
        if error is not None and not any(c.error <= error for c in cands):
            b = min(cands, key=lambda c: (c.error, c.seconds))
            s = b.setting
            if b.e_space >= b.e_time:
                why = f"the spatial error of the scene's shapes at p = {s.p} ({b.e_space:.2g})"
            elif s.p == max(P_CHOICES) or "p" in self.fixed:
                why = (f"the time error of {s.scheme} at the smallest E/T of the model, {min(TOL_GRID):g} "
                       f"({b.e_time:.2g}), at p = {s.p}" + (" (given)" if "p" in self.fixed else ", the largest p"))
            else:
                why = f"the time error of {s.scheme} at E/T = {s.tol:.3g} ({b.e_time:.2g})"
            return (f"error {error:g} cannot be reached: the best reachable is {b.error:.2g} ({s.scheme}, p = {s.p}, "
                    f"E/T = {s.tol:.3g}, {b.seconds:.3g} s CPU), limited by {why}")
        fit = [c for c in cands if error is None or c.error <= error]
        b = min(fit, key=lambda c: c.seconds)
        what = "" if error is None else f" at error {error:g}"
        return (f"budget {budget:g} s cannot be met{what}: the cheapest is {b.seconds:.3g} s CPU ({b.setting.scheme}, "
                f"p = {b.setting.p}, E/T = {b.setting.tol:.3g}, error {b.error:.2g}), limited by the cost of a solve "
                f"at p = {b.setting.p} ({b.solves:.0f} solves)")


def fixed_from_options(getter):
    """The settings the user gave on the command line (the plan keeps them)."""
    fixed = {}
    for name, key, typ in (("-ves_p", "p", int), ("-ts_type", "scheme", str), ("-ves_adapt_tol", "tol", float),
                           ("-ves_repulsion_radius", "R", float)):
        raw = getter(name, typ, None)
        if raw is not None:
            fixed[key] = optmod.parse_value(name, raw)
    return fixed


def plan_record(best, runner_up, target, budget, model):
    """What `vesflow run` stores in the output file's attribute `plan` (JSON)."""
    rec = {"error_target": target, "budget": budget, "chosen": asdict(best.setting),
           "predicted_error": best.error, "predicted_seconds": best.seconds, "predicted_solves": best.solves,
           "options": shlex.join(best.setting.argv()), "model": model.fit["source"], "pilot": model.pilot}
    if runner_up is not None:
        rec["runner_up"] = dict(asdict(runner_up.setting), predicted_error=runner_up.error,
                                predicted_seconds=runner_up.seconds)
    return rec


def plan_for_run(scene, args):
    """`vesflow run` of a scene with [accuracy]: (plan options to put before the command line's,
    the one line that says what was chosen, the record for the output file)."""
    getter = optmod.argv_getter(args)
    sc = optmod.apply_overrides(scene, getter)
    pl = Planner(sc, fixed=fixed_from_options(getter))
    best, runner = pl.plan(error=scene.accuracy.error)
    line = (f"vesflow: plan for [accuracy] error {scene.accuracy.error:g}: {best.setting.describe()}; predicted "
            f"error {best.error:.2g}, {best.seconds:.3g} s CPU")
    return best.setting.argv(), line, plan_record(best, runner, scene.accuracy.error, None, pl.model)

"""What accuracy costs in time: the paper's Table 3 experiment (section 4.1, Fig. 5).

Two vesicles in shear are run once as a reference (high p, tight adaptivity tolerance, no
repulsion) and then for a grid of cases (p, E, R_repul).  For each case: the error in vesicle
position (centroid, normalized by the vesicle length, max over vesicles) against the reference
at the end of the horizon, the number of implicit solves N_Tstep, the average GMRES iterations
per solve N_iter, the time to solution T_solve and its split into setup, self, near, far and
reparameterization (the PETSc log events of vesflow.timing).

Tolerances: the paper's E is the error allowed over the horizon T; the run option is the rate
``-ves_adapt_tol = E / T``.  The table shows both.

Every finished case is stored as JSON in ``OUT/cases/`` (keyed by the scene text and the case),
so an interrupted study resumes where it stopped; ``--fresh`` recomputes.
"""
from __future__ import annotations

import csv
import hashlib
import json
import os
import platform
import sys
import time
from dataclasses import dataclass

import numpy as np

from . import collision, options as optmod, scene as scenemod
from .errors import NumericalFailure, SceneError, VesflowError
from .simulation import Run
from .surface import Surface


SCHEMES = ("euler", "sdc")      # -ts_type; euler with step doubling, sdc with its sweep estimate


def scheme_options(scheme):
    """The run options of a study scheme: "euler", "sdc" (the defaults of -ts_sdc_*) or
    "sdc-QUADn" / "sdc-QUADnxk" (QUAD lobatto or radau, n = -ts_sdc_nodes, k = -ts_sdc_sweeps),
    e.g. "sdc-radau4x2"; ValueError naming the scheme otherwise."""
    import re
    base, _, variant = scheme.partition("-")
    m = re.fullmatch(r"(lobatto|radau)(\d)(?:x(\d+))?", variant) if variant else None
    if base not in SCHEMES or (variant and (base != "sdc" or m is None)):
        raise ValueError(f"scheme {scheme!r}: must be euler, sdc or sdc-QUADn[xk] (QUAD lobatto or radau, "
                         "n nodes 2-9, k sweeps), e.g. sdc-radau4x2")
    given = {"-ts_type": base, "-ves_adapt": "doubling" if base == "euler" else "sweeps"}
    if m is not None:
        given["-ts_sdc_quadrature"] = m.group(1)
        given["-ts_sdc_nodes"] = int(m.group(2))
        if m.group(3):
            given["-ts_sdc_sweeps"] = int(m.group(3))
    return given


@dataclass(frozen=True)
class Case:
    """One run of the study: degree p, adaptivity rate tol = E / T, repulsion radius R (0: off),
    time integrator scheme (-ts_type, default options of each)."""

    p: int
    tol: float
    R: float = 0.0
    scheme: str = "euler"

    @property
    def key(self):
        return f"p{self.p}_tol{self.tol:g}_R{self.R:g}" + ("" if self.scheme == "euler" else f"_{self.scheme}")


# The paper's Table 3 (T = 160, p = 32 reference, E / T from 1.25e-3 to 1.5e-2) rescaled to a
# horizon and degrees that this machine runs in about an hour; E / T spans a factor 8 as there.
FULL_REFERENCE = Case(16, 2.5e-3, 0.0)
FULL_CASES = (
    Case(16, 1e-2), Case(16, 2e-2), Case(16, 4e-2),                          # fixed p, no repulsion
    Case(12, 1e-2, 0.02), Case(10, 2e-2, 0.04), Case(8, 4e-2, 0.06),         # low p made possible by repulsion
    Case(12, 1e-2), Case(8, 4e-2),                                            # low p without repulsion
)
QUICK_HORIZON = 1.5
QUICK_REFERENCE = Case(10, 1.25e-3, 0.0)
QUICK_CASES = (Case(10, 5e-3), Case(10, 2e-2), Case(8, 5e-3), Case(8, 2e-2, 0.06))


class Recorder:
    """An in-memory stand-in for io.OutputWriter: keeps every step row and frame summary."""

    def __init__(self, q_gap):
        self.steps, self.frames, self.timings, self.q_gap = [], [], {}, q_gap

    def write_steps(self, rows):
        self.steps.extend(rows)

    def write_frame(self, *, time, coefficients, centroid, area, volume, **_):
        S = Surface(coefficients, int(round(np.sqrt(coefficients.shape[-1] + 1))) - 1)
        gap = collision.min_gap(S, self.q_gap) if S.n_vesicles > 1 else np.inf
        self.frames.append({"time": float(time), "centroid": np.asarray(centroid).tolist(),
                            "area": np.asarray(area).tolist(), "volume": np.asarray(volume).tolist(),
                            "min_gap": float(gap)})

    def write_timings(self, timings):
        self.timings = dict(timings)

    def write_checkpoint(self, checkpoint):
        pass


def case_scene(scene, case, horizon=None):
    """The scene with the case's p, repulsion and (optionally) a shorter horizon, and frames only
    at t = 0 and at the horizon: steps land on every output time (docs/explanation/dynamics.md), and the
    landings the scene's output times would add are not part of what a tolerance costs (the
    first study, before landing steps existed, had none).  The smallest gap of the table is
    then the one at the horizon, where the study's scene has its closest approach."""
    T = scene.time.horizon if horizon is None else horizon
    over = {"-ves_p": case.p, "-ves_repulsion_radius": case.R, "-ves_output_every": T}
    if horizon is not None:
        over["-ts_max_time"] = horizon
    return optmod.apply_overrides(scene, optmod.dict_getter(over))


def run_case(scene, case, horizon=None, extra_options=None):
    """Run one case; returns a dict of the measured figures (status 'ok' or 'failed: ...')."""
    sc = case_scene(scene, case, horizon)
    given = dict(scheme_options(case.scheme), **{"-ves_adapt_tol": case.tol})
    given.update(extra_options or {})
    opts = optmod.read_options(optmod.dict_getter(given), sc)
    rec = Recorder(opts["q_near"])
    t0, c0 = time.perf_counter(), time.process_time()
    status, run = "ok", None
    try:
        run = Run(sc, opts, writer=rec)
        run.run()
    except (NumericalFailure, VesflowError) as e:
        status = f"failed: {e}"
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    steps = rec.steps
    solves_per_try = 3 if given["-ves_adapt"] == "doubling" else 1
    if opts["ts_type"] == "sdc":    # vesflow.sdc: M (2K + 1) + 1 solves per step, M = nodes - 1
        solves_per_try *= ((opts["ts_sdc_nodes"] - 1) * (2 * opts["ts_sdc_sweeps"] + 1)
                           + (opts["ts_sdc_quadrature"] == "lobatto"))
    n_solves = solves_per_try * len(steps)
    its = sum(int(r[3]) for r in steps)
    reasons = {}
    for r in steps:
        if r[5] != "accepted":
            reasons[r[5]] = reasons.get(r[5], 0) + 1
    final = None
    if run is not None and status == "ok":
        S = run.stepper.surface
        ext = np.linalg.norm(S.points() - S.centroid()[:, None, :], axis=-1).max(axis=1)
        final = {"centroid": S.centroid().tolist(), "length": (2 * ext).tolist(),
                 "area_error": float(np.abs(S.area() / run.area0 - 1).max()),
                 "volume_error": float(np.abs(S.volume() / run.volume0 - 1).max())}
    tm = rec.timings or (run.timers.as_dict() if run is not None else {})
    gaps = [f["min_gap"] for f in rec.frames if np.isfinite(f["min_gap"])]
    return {"p": case.p, "tol": case.tol, "R": case.R, "scheme": case.scheme, "E": case.tol * sc.time.horizon,
            "status": status,
            "horizon": sc.time.horizon, "accepted": sum(1 for r in steps if r[2]), "rejected": reasons,
            "n_solves": n_solves, "avg_its": its / max(n_solves, 1), "wall": wall, "cpu": cpu,
            "timers": {k: float(v) for k, v in tm.items()}, "min_gap": min(gaps) if gaps else None,
            "frames": rec.frames, "final": final}


def position_error(res, ref):
    """max_i |c_i - c_i^ref| / L_i^ref (paper 4.1.1), or None if either run failed."""
    if res["final"] is None or ref["final"] is None:
        return None
    c, cr = np.asarray(res["final"]["centroid"]), np.asarray(ref["final"]["centroid"])
    return float((np.linalg.norm(c - cr, axis=1) / np.asarray(ref["final"]["length"])).max())


def _cache_path(out, scene_text, case, horizon):
    h = hashlib.sha256(f"{scene_text}|{horizon}".encode()).hexdigest()[:10]
    return os.path.join(out, "cases", f"{h}_{case.key}.json")


def cached_run(scene, case, out, horizon=None, fresh=False, log=print):
    path = _cache_path(out, scene.text or "", case, horizon)
    if not fresh and os.path.exists(path):
        with open(path) as f:
            res = json.load(f)
        log(f"  {case.key}: cached ({path})")
        return res
    log(f"  {case.key}: running ...")
    res = run_case(scene, case, horizon)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump(res, f)
    log(f"  {case.key}: {res['status']}, {res['n_solves']} solves, {res['avg_its']:.1f} its, "
        f"{res['wall']:.1f} s wall")
    return res


COLUMNS = ("scheme", "p", "E", "tol", "R", "error", "N_Tstep", "N_iter", "T_solve", "T_setup", "T_self", "T_near",
           "T_far", "T_repar", "cpu", "rejected", "min_gap", "status")


def table_rows(results, ref):
    rows = []
    for r in results:
        tm = r["timers"]
        err = position_error(r, ref)
        rows.append({"scheme": r.get("scheme", "euler"), "p": r["p"], "E": r["E"], "tol": r["tol"], "R": r["R"], "error": err,
                     "N_Tstep": r["n_solves"], "N_iter": r["avg_its"], "T_solve": r["wall"],
                     "T_setup": tm.get("setup", 0.0), "T_self": tm.get("self", 0.0), "T_near": tm.get("near", 0.0),
                     "T_far": tm.get("far", 0.0), "T_repar": tm.get("repar", 0.0), "cpu": r["cpu"],
                     "rejected": " ".join(f"{k}:{v}" for k, v in sorted(r["rejected"].items())) or "0",
                     "min_gap": r["min_gap"], "status": r["status"].split(":")[0]})
    return rows


def _fmt(v, col):
    if v is None:
        return "-"
    if col in ("p", "N_Tstep"):
        return str(int(v))
    if col == "N_iter":
        return f"{v:.1f}"
    if col.startswith("T_") or col == "cpu":
        return f"{v:.1f}"
    if isinstance(v, float):
        return f"{v:.2g}" if col in ("R",) else f"{v:.2e}" if col != "E" else f"{v:.3g}"
    return str(v)


def markdown(rows):
    head = "| " + " | ".join(COLUMNS) + " |\n|" + "---|" * len(COLUMNS) + "\n"
    return head + "".join("| " + " | ".join(_fmt(r[c], c) for c in COLUMNS) + " |\n" for r in rows)


def pareto(rows):
    """Rows not dominated in (process CPU time, error): the cheapest way to each accuracy (CPU,
    not wall: on a shared machine the wall time depends on the other jobs)."""
    ok = sorted((r for r in rows if r["error"] is not None), key=lambda r: (r["cpu"], r["error"]))
    front, best = [], np.inf
    for r in ok:
        if r["error"] < best:
            front.append(r)
            best = r["error"]
    return front


def plot(rows, path, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6.4, 4.6))
    schemes = sorted({r.get("scheme", "euler") for r in rows}, key=lambda s: (s != "euler", s))
    markers = dict(zip(schemes, "o^vDP*Xph"))
    for scheme in schemes:
        for R in (0.0, None):
            sel = [r for r in rows if r["error"] is not None and ((r["R"] == 0) == (R == 0.0))
                   and r.get("scheme", "euler") == scheme]
            if not sel:
                continue
            sc = ax.scatter([r["cpu"] for r in sel], [r["error"] for r in sel], c=[r["p"] for r in sel],
                            cmap="viridis", marker=markers[scheme], s=46, vmin=6, vmax=16,
                            edgecolors="none" if R == 0.0 else "red",
                            label=f"{scheme}, " + ("no repulsion" if R == 0.0 else "repulsion"))
            for r in sel:
                ax.annotate(f"{scheme} p{r['p']} E/T={r['tol']:g}" + (f" R={r['R']:g}" if r["R"] else ""),
                            (r["cpu"], r["error"]), fontsize=6, xytext=(3, 3), textcoords="offset points")
    front = pareto(rows)
    if front:
        ax.plot([r["cpu"] for r in front], [r["error"] for r in front], "k--", lw=0.8, label="Pareto front")
    failed = [r for r in rows if r["error"] is None]
    for k, r in enumerate(failed):
        ax.annotate(f"p{r['p']} E/T={r['tol']:g} R={r['R']:g}: {r['status']}", (0.02, 0.04 + 0.05 * k),
                    xycoords="axes fraction", fontsize=6, color="red")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("CPU time of the run [s]")
    ax.set_ylabel("position error / vesicle length")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    if rows:
        fig.colorbar(sc, ax=ax, label="p")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def fitted_rate(xs, ys):
    """Slope of log y against log x (least squares)."""
    xs, ys = np.log(np.asarray(xs, float)), np.log(np.asarray(ys, float))
    return float(np.polyfit(xs, ys, 1)[0]) if len(xs) >= 2 else float("nan")


def accuracy_cost(scene_path, out, quick=False, reference=None, cases=None, fresh=False, log=print):
    """Run the study; write OUT/accuracy_cost.{csv,md,png}; return (rows, reference result)."""
    scene = scenemod.load_scene(scene_path)
    horizon = QUICK_HORIZON if quick else None
    reference = reference or (QUICK_REFERENCE if quick else FULL_REFERENCE)
    cases = list(cases or (QUICK_CASES if quick else FULL_CASES))
    os.makedirs(out, exist_ok=True)
    log(f"vesflow study accuracy-cost: {scene_path}, {'quick' if quick else 'full'}, reference {reference.key}, "
        f"{len(cases)} cases -> {out}")
    ref = cached_run(scene, reference, out, horizon, fresh, log)
    if ref["status"] != "ok":
        raise NumericalFailure(f"the reference run {reference.key} failed ({ref['status']}); choose another "
                               "reference (--ref p,tol,R)")
    results = [cached_run(scene, c, out, horizon, fresh, log) for c in cases]
    rows = table_rows(results, ref)
    with open(os.path.join(out, "accuracy_cost.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)
    T = ref["horizon"]
    fixed_p = [r for r in rows if r["p"] == reference.p and r["R"] == 0 and r["error"] and r["scheme"] == "euler"]
    lines = [f"# Accuracy and cost: {scene.title}", "",
             f"Scene `{scene_path}`, horizon T = {T:g}, reference {reference.key} "
             f"({ref['n_solves']} solves, {ref['wall']:.0f} s).  Machine: {platform.machine()}, "
             f"{os.cpu_count()} cpus, load average at the end {os.getloadavg()[0]:.2f}; "
             f"OMP_NUM_THREADS = {os.environ.get('OMP_NUM_THREADS', 'unset')}.", "",
             "E = tol * T is the paper's tolerance over the horizon; tol = `-ves_adapt_tol`; times in seconds "
             "(wall, PETSc log events); N_Tstep counts implicit solves (3 per attempted step with step "
             "doubling, 11 per sdc step with 3 nodes and 2 sweeps); rejected: reason:count; min_gap: smallest surface gap seen at the frames.", "",
             markdown(rows)]
    if len(fixed_p) >= 2:
        lines += ["", f"Fitted at p = {reference.p}, no repulsion: error ~ E^{fitted_rate([r['E'] for r in fixed_p], [r['error'] for r in fixed_p]):.2f}, "
                  f"N_Tstep ~ E^{fitted_rate([r['E'] for r in fixed_p], [r['N_Tstep'] for r in fixed_p]):.2f} "
                  "(paper: error linear in E, steps ~ 1/E)."]
    front = pareto(rows)
    if front:
        lines += ["", "Pareto front (cheapest run for each accuracy): " +
                  ", ".join(f"{r['scheme']} p{r['p']} E/T={r['tol']:g} R={r['R']:g} ({r['error']:.1e}, {r['cpu']:.0f} s CPU)"
                            for r in front)]
    with open(os.path.join(out, "accuracy_cost.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    plot(rows, os.path.join(out, "accuracy_cost.png"), f"{scene.title}, T = {T:g} (reference {reference.key})")
    log("\n".join(lines))
    return rows, ref


def parse_case(text):
    """'p,tol[,R[,scheme]]' -> Case (one-line SceneError on bad input)."""
    items = text.split(",")
    scheme = items.pop() if len(items) == 4 else "euler"
    try:
        parts = [float(x) for x in items]
        if len(parts) not in (2, 3) or parts[0] != int(parts[0]) or parts[0] < 2 or parts[1] <= 0 \
                or (len(parts) == 3 and parts[2] < 0):
            raise ValueError
        scheme_options(scheme)
    except ValueError:
        raise SceneError(f"case {text!r}: expected p,tol[,R[,scheme]] with integer p >= 2, tol > 0, R >= 0, "
                         "scheme euler, sdc or sdc-QUADn[xk] (e.g. sdc-radau4x2)") from None
    return Case(int(parts[0]), parts[1], parts[2] if len(parts) == 3 else 0.0, scheme)


USAGE = ("usage: vesflow study accuracy-cost [SCENE.toml] [--out DIR] [--quick] [--ref p,tol,R[,scheme]] "
         "[--case p,tol,R[,scheme] ...] [--fresh]  (scheme: euler, sdc or sdc-QUADn[xk], e.g. sdc-radau4x2: "
         "-ts_type sdc -ts_sdc_quadrature radau -ts_sdc_nodes 4 -ts_sdc_sweeps 2)")


def main(argv):
    """`vesflow study accuracy-cost ...` (returns the exit status)."""
    if not argv or argv[0] in ("-h", "--help", "-help"):
        print(USAGE)
        return 0 if argv else 2
    if argv[0] != "accuracy-cost":
        raise SceneError(f"unknown study {argv[0]!r}: the study is accuracy-cost")
    rest = argv[1:]
    scene_path, out, quick, ref, cases, fresh = "runs/accuracy_cost.toml", None, False, None, [], False
    pairs, others = optmod.take_valued(rest, ("--out", "--ref", "--case"))
    for name, v in pairs:
        if name == "--out":
            out = v
        elif name == "--ref":
            ref = parse_case(v)
        else:
            cases.append(parse_case(v))
    for a in others:
        if a == "--quick":
            quick = True
        elif a == "--fresh":
            fresh = True
        elif a.startswith("-"):
            raise SceneError(f"{a}: unknown study option; {USAGE}")
        else:
            scene_path = a
    out = out or ("out/study_quick" if quick else "docs/study")
    accuracy_cost(scene_path, out, quick=quick, reference=ref, cases=cases or None, fresh=fresh)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

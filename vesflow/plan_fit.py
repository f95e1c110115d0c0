"""The planner's measurements (vesflow.planner): fitting its constants to the accuracy-cost
study, pilot runs that calibrate them on a scene, and runs of a plan against a reference.

    python -m vesflow.plan_fit fit [STUDY_DIR ...]            print FIT from the study's cached cases
    python -m vesflow.plan_fit reference SCENE --out DIR [-ts_max_time T]   a p = 16, E/T = 1e-4 sdc run
    python -m vesflow.plan_fit verify SCENE --error E --ref REF.json [--out DIR] [--pilot F] [-ts_max_time T]
    python -m vesflow.plan_fit table [DIR]       the verify runs against the grid (markdown)
    python -m vesflow.plan_fit grid SCENE --ref REF.json --out DIR [--only scheme,p,tol] [-ts_max_time T]
                                                the study's grid of settings run on the scene

A run's error against another (`distance`): max over vesicles of the centroid difference
(minimum image in a periodic cell) and of the difference of the semi-axes of the equivalent
ellipsoid (the eigenvalues of the volume's second moments), over the reference's vesicle
length; the study's cached reference has centroids only, so against it the error is the
study's position error.
"""
from __future__ import annotations

import glob
import json
import os
import sys
import time

import numpy as np
from scipy.optimize import nnls

from . import options as optmod, planner, scene as scenemod, study
from .errors import NumericalFailure, SceneError, VesflowError
from .simulation import Run
from .surface import Surface

STUDY_DIRS = ("docs/study",)
REFERENCE = study.Case(16, 1e-4, 0.0, "sdc")
PILOT_P = (8, 12)
PILOT_TOL = 2e-2


# ----------------------------------------------------------------------------- runs
def semi_axes(S):
    """(N, 3) semi-axes of the ellipsoid with each vesicle's volume second moments:
    int_V x_i x_j dV = (1/5) int (x_i x_j)(x . n) dA with x from the centroid; a_k = sqrt(5 l_k / V)."""
    g = S.geometry(2 * S.p)
    x = g.X - S.centroid()[:, None, :]
    xn = np.einsum("nik,nik->ni", x, g.normal)
    M = np.einsum("nia,nib,ni,ni->nab", x, x, xn, g.dA) / 5.0
    return np.sqrt(5.0 * np.clip(np.linalg.eigvalsh(M), 0, None) / S.volume()[:, None])


def run_setting(scene, setting, horizon=None):
    """Run the scene with a planner.Setting (frames at 0 and the horizon only, as the study);
    returns a JSON-able dict: status, cpu, wall, solves, steps, final centroid / length / axes."""
    case = study.Case(setting.p, setting.tol, setting.R, setting.scheme)
    sc = study.case_scene(scene, case, horizon)
    given = dict(study.scheme_options(setting.scheme), **setting.options())
    opts = optmod.read_options(optmod.dict_getter(given), sc)
    rec = study.Recorder(opts["q_near"])
    t0, c0 = time.perf_counter(), time.process_time()
    status, run = "ok", None
    try:
        run = Run(sc, opts, writer=rec, log=lambda *a, **k: None)
        run.run()
    except (NumericalFailure, VesflowError) as e:
        status = f"failed: {e}"
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    per_try = 3 if given["-ves_adapt"] == "doubling" else 1
    if opts["ts_type"] == "sdc":
        per_try *= (opts["ts_sdc_nodes"] - 1) * (2 * opts["ts_sdc_sweeps"] + 1) + (opts["ts_sdc_quadrature"] == "lobatto")
    out = {"setting": setting.options(), "status": status, "horizon": sc.time.horizon, "cpu": cpu, "wall": wall,
           "solves": per_try * len(rec.steps), "accepted": sum(1 for r in rec.steps if r[2]),
           "rejected": sum(1 for r in rec.steps if not r[2]), "final": None,
           "floor_tol": floor_tol(rec.steps, planner.fewest_steps(sc.time.horizon, sc.time.dt),
                                  opts["adapt_beta"], run.integrator.order) if run is not None else None}
    if run is not None and status == "ok":
        S = run.stepper.surface
        ext = np.linalg.norm(S.points() - S.centroid()[:, None, :], axis=-1).max(axis=1)
        out["final"] = {"centroid": run.unwrapped_centroid().tolist(), "length": (2 * ext).tolist(),
                        "axes": semi_axes(S).tolist()}
    return out


def floor_tol(steps, fewest, beta, order):
    """The smallest E/T at which a run that took exactly the fewest steps (each accepted, dt
    doubling) takes the same steps: every step's err / dt <= E/T, and every step but the last
    (which lands on the horizon) proposes 2 dt, beta ((E/T) dt / err)^(1/k) >= 2 (vesflow.stepping.
    Adaptor.next_dt).  None if the run took more steps.  steps: the rows (t, dt, accepted, its,
    err, ...)."""
    if len(steps) != fewest or not all(r[2] for r in steps):
        return None
    rate = [max(float(r[4]), 0.0) / float(r[1]) for r in steps]
    grow = (2.0 / beta) ** order
    return max([x * grow for x in rate[:-1]] + [rate[-1]])


def distance(res, ref, period=None):
    """Error of run `res` against run `ref` (module docstring); None if either failed."""
    a, b = res.get("final"), ref.get("final")
    if a is None or b is None:
        return None
    d = np.asarray(a["centroid"]) - np.asarray(b["centroid"])
    if period:
        d -= period * np.round(d / period)
    err = np.linalg.norm(d, axis=1)
    if "axes" in a and "axes" in b:
        err = np.maximum(err, np.abs(np.asarray(a["axes"]) - np.asarray(b["axes"])).max(axis=1))
    return float((err / np.asarray(b["length"])).max())


def cached(path, compute, log=print):
    if os.path.exists(path):
        with open(path) as f:
            return json.load(f)
    res = compute()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(res, f)
    log(f"  wrote {path}")
    return res


# ----------------------------------------------------------------------------- the fit
def study_cases(dirs=STUDY_DIRS):
    """(reference, cases) of the study's cached case files (later directories override)."""
    by_key, ref = {}, None
    for d in dirs:
        for path in sorted(glob.glob(os.path.join(d, "cases", "*.json"))):
            with open(path) as f:
                res = json.load(f)
            case = study.Case(res["p"], res["tol"], res["R"], res.get("scheme", "euler"))
            if case == REFERENCE:
                ref = res
            else:
                by_key[case.key] = res
    if ref is None:
        raise SceneError(f"no reference case {REFERENCE.key} in {', '.join(dirs)}")
    return ref, [r for r in by_key.values() if r["status"] == "ok"]


def _loglinear(x, y):
    """y = A x^a by least squares in logs: (A, a)."""
    a, logA = np.polyfit(np.log(x), np.log(y), 1)
    return float(np.exp(logA)), float(a)


def fit_from_study(dirs=STUDY_DIRS, scene_path="runs/accuracy_cost.toml"):
    """The planner's FIT from the study's cases (see vesflow.planner)."""
    ref, cases = study_cases(dirs)
    pref, T = REFERENCE.p, ref["horizon"]
    for r in cases:
        r["error"] = study.position_error(r, ref)
    fit = {"source": f"{', '.join(dirs)} ({scene_path}; reference {REFERENCE.scheme} p = {pref}, "
                     f"E/T = {REFERENCE.tol:g})", "horizon": T, "n_vesicles": len(ref["final"]["centroid"]),
           "p_ref": pref, "time": {}, "solves": {}, "cost": {}}
    for scheme in planner.SCHEMES:
        top = [r for r in cases if r["scheme"] == scheme and r["p"] == pref and r["R"] == 0]
        A, a = _loglinear([r["tol"] / 1e-2 for r in top], [r["error"] for r in top])
        fit["time"][scheme] = {"A": A, "a": a}
        mine = [r for r in cases if r["scheme"] == scheme]
        s, mb = _loglinear([r["tol"] / 1e-2 for r in mine], [r["n_solves"] / T for r in mine])
        fit["solves"][scheme] = {"s": s, "b": -mb}
    low = []
    for r in cases:
        if r["p"] < pref:
            t = fit["time"][r["scheme"]]
            rest = r["error"] - t["A"] * (r["tol"] / 1e-2) ** t["a"]
            if rest > 0.2 * r["error"]:
                low.append((r["p"], rest))
    ps, es = np.array([x[0] for x in low], float), np.array([x[1] for x in low])
    best = None
    for rr in np.linspace(0.3, 0.98, 681):
        basis = rr ** ps - rr ** pref
        logA = float(np.mean(np.log(es) - np.log(basis)))
        res = float(np.sum((np.log(es) - logA - np.log(basis)) ** 2))
        if best is None or res < best[0]:
            best = (res, float(np.exp(logA)), float(rr))
    fit["spatial"] = {"A": best[1], "r": best[2]}
    scene = scenemod.load_scene(scene_path)
    for scheme in planner.SCHEMES:
        mine = [r for r in cases if r["scheme"] == scheme]
        ts = np.array([planner.t_solve(scene, planner.Setting(scheme, r["p"], r["tol"], 2 * r["p"], 2 * r["p"]))[0]
                       for r in mine])
        y = np.array([r["cpu"] / r["n_solves"] for r in mine])
        N = fit["n_vesicles"]
        X = np.column_stack([ts / y, N * np.ones_like(y) / y])        # relative residuals
        (k, c), *_ = np.linalg.lstsq(X, np.ones_like(y), rcond=None)
        fit["cost"][scheme] = {"k": float(k), "c": float(c)}
    return fit


def in_sample(fit, dirs=STUDY_DIRS, scene_path="runs/accuracy_cost.toml", log=print):
    """The fitted model against the cases it was fitted to (a markdown table)."""
    ref, cases = study_cases(dirs)
    pl = planner.Planner(scenemod.load_scene(scene_path), planner.Model(fit))
    log("| scheme | p | E/T | error | predicted | solves | predicted | CPU s | predicted |\n|---|---|---|---|---|---|---|---|---|")
    for r in sorted(cases, key=lambda r: (r["scheme"], r["p"], r["tol"])):
        e = study.position_error(r, ref)
        pr = pl.predict(planner.Setting(r["scheme"], r["p"], r["tol"], 2 * r["p"], 2 * r["p"], r["R"]))
        log(f"| {r['scheme']} | {r['p']} | {r['tol']:g} | {e:.2e} | {pr.error:.2e} ({pr.error / e:.2f}) | "
            f"{r['n_solves']} | {pr.solves:.0f} | {r['cpu']:.1f} | {pr.seconds:.1f} ({pr.seconds / r['cpu']:.2f}) |")


# ----------------------------------------------------------------------------- pilots
def calibrate(scene, pl, fraction=1.0, log=print, cache_dir=None):
    """Pilot runs to fraction * T on the scene: sdc at p = 8 with E/T = 2e-2 and 5e-3, euler at
    p = 8 with 2e-2, sdc at p = 12 with 2e-2.  Their differences give the scene's time errors
    (sdc: the two tolerances; euler: against the tighter sdc run) and spatial error (p = 8
    against 12), their solves and CPU the solve counts and cost per solve; each as a factor on
    the model's prediction for the pilot horizon.  Returns the calibrated planner.Model."""
    m0 = pl.model
    t_p = fraction * scene.time.horizon
    lo, hi = PILOT_P
    runs = {"sdc_lo": ("sdc", lo, PILOT_TOL), "sdc_lo_fine": ("sdc", lo, PILOT_TOL / 4),
            "euler_lo": ("euler", lo, PILOT_TOL), "sdc_hi": ("sdc", hi, PILOT_TOL)}
    R = scene.repulsion.radius if scene.repulsion is not None else 0.0
    sets = {k: planner.Setting(s, p, tol, 2 * p, 2 * p, R) for k, (s, p, tol) in runs.items()}
    sub = optmod.apply_overrides(scene, optmod.dict_getter({"-ts_max_time": t_p}))
    sub_pl = planner.Planner(sub, m0)
    if sub_pl._solve_cost(sets["euler_lo"])[1] not in ("none", "direct"):
        # a far field with a tolerance: a fifth pilot at the loosest, the cost at another t_solve of one p
        sets["euler_lo_far"] = planner.replace(sets["euler_lo"], far_tol=planner.FAR_TOLS[0])
    predicted = sum(sub_pl.predict(s).seconds for s in sets.values())
    log(f"pilot    {len(sets)} runs to t = {t_p:g} ({fraction:g} of T): predicted {predicted:.3g} s CPU")
    c0 = time.process_time()
    if cache_dir is None:
        out = {k: run_setting(scene, s, t_p) for k, s in sets.items()}
    else:                                    # plan_fit verify: the pilots once per scene
        stem = f"{os.path.basename(scene.source).split('.')[0]}_T{scene.time.horizon:g}_t{t_p:g}"
        out = {k: cached(os.path.join(cache_dir, "pilot", f"{stem}_{k}.json"), lambda s=s: run_setting(scene, s, t_p),
                         log=log) for k, s in sets.items()}
    bad = [k for k, r in out.items() if r["final"] is None]
    if bad:
        raise NumericalFailure(f"pilot run {bad[0]} failed ({out[bad[0]]['status']})")
    period = scene.periodic_length or None
    m = planner.Model(m0.fit)
    clip = lambda x: float(min(max(x, 1e-4), 1e4))
    a_sdc = m0.fit["time"]["sdc"]["a"]
    e_sdc = distance(out["sdc_lo"], out["sdc_lo_fine"], period) / max(1 - 4.0 ** -a_sdc, 0.1)
    e_eul = distance(out["euler_lo"], out["sdc_lo_fine"], period)
    e_sp = distance(out["sdc_lo"], out["sdc_hi"], period)
    s_lo, s_hi = m0.e_space(lo, t_p), m0.e_space(hi, t_p)
    m.f_time = {"sdc": clip(e_sdc / m0.e_time("sdc", PILOT_TOL, t_p)),
                "euler": clip(e_eul / m0.e_time("euler", PILOT_TOL, t_p))}
    m.f_space = clip(e_sp / max(s_lo - s_hi, 1e-300))
    m.split = cost_split(scene, sub_pl, sets, out)
    whole = t_p >= scene.time.horizon * (1 - 1e-12)
    for scheme in planner.SCHEMES:
        keys = [k for k in sets if sets[k].scheme == scheme]
        # above the fewest steps only (a pilot that took them says nothing about the rate)
        floor = planner.SOLVES_PER_STEP[scheme] * planner.fewest_steps(t_p, scene.time.dt)
        m.f_solves[scheme] = clip(np.mean([max(out[k]["solves"], floor) / m0.solves(scheme, sets[k].tol, t_p)
                                           for k in keys if k in ("sdc_lo", "sdc_hi", "euler_lo")]))
        # where every pilot of the scheme took the fewest steps over the whole horizon: from which E/T on
        fl = [out[k].get("floor_tol") for k in keys]
        m.floor_tol[scheme] = max(fl) if whole and all(x is not None for x in fl) else None
        m.f_cost[scheme] = clip(np.exp(np.mean([np.log(out[k]["cpu"] / out[k]["solves"] /
                                                      m.seconds_per_solve(scheme, sub_pl._solve_cost(sets[k])[0],
                                                                          scene.n_vesicles)) for k in keys])))
    spent = sum(r["cpu"] for r in out.values()) if cache_dir else time.process_time() - c0
    fewest = " / ".join(f"{s} " + (f"E/T >= {m.floor_tol[s]:.2g}" if m.floor_tol[s] is not None else "-")
                        for s in planner.SCHEMES)
    m.pilot = (f"calibrated by {len(sets)} pilot runs to t = {t_p:g} ({spent:.3g} s CPU): factors spatial {m.f_space:.2g}, "
               f"time sdc {m.f_time['sdc']:.2g} / euler {m.f_time['euler']:.2g}, solves sdc {m.f_solves['sdc']:.2g} / "
               f"euler {m.f_solves['euler']:.2g}, fewest steps {fewest}, cost split alpha {m.split[0]:.2g} / beta "
               f"{m.split[1]:.2g}, cost sdc {m.f_cost['sdc']:.2g} / euler {m.f_cost['euler']:.2g}")
    log(f"pilot    {m.pilot}")
    return m


def cost_split(scene, pl, sets, out):
    """(alpha, beta) of the scene's cost per solve alpha k t_solve + beta c N (k, c: the study's,
    fitted on two vesicles) from the pilots' CPU per solve: non-negative least squares in the
    relative residuals (the pilots differ in t_solve by p and, for a far field with a tolerance,
    by it; all have the scene's N).  (1, 1) where the pilots do not determine both (fewer than
    two values of t_solve, or alpha = 0)."""
    rows, y = [], []
    for key, s in sets.items():
        c = pl.model.fit["cost"][s.scheme]
        rows.append([c["k"] * pl._solve_cost(s)[0], c["c"] * scene.n_vesicles])
        y.append(out[key]["cpu"] / out[key]["solves"])
    A, y = np.array(rows), np.array(y)
    if len({round(pl._solve_cost(s)[0], 12) for s in sets.values()}) < 2:
        return (1.0, 1.0)
    (al, be), _ = nnls(A / y[:, None], np.ones_like(y))
    return (float(al), float(be)) if al > 0 else (1.0, 1.0)


# ----------------------------------------------------------------------------- verification
def grid_settings():
    """The study's grid: the (scheme, p, E/T) of its cases (repulsion off, q = 2p)."""
    _, cases = study_cases()
    keys = sorted({(r["scheme"], r["p"], r["tol"]) for r in cases})
    return [planner.Setting(s, p, tol, 2 * p, 2 * p) for s, p, tol in keys]


def grid(sc, path, ref, out, only=None):
    """Run (cached) every grid setting on the scene; print error and CPU of each."""
    stem = f"{os.path.basename(path).split('.')[0]}_T{sc.time.horizon:g}"
    for s in grid_settings():
        if only and only != f"{s.scheme},{s.p},{s.tol:g}":
            continue
        res = cached(os.path.join(out, "grid", f"{stem}_{s.scheme}_p{s.p}_tol{s.tol:g}.json"),
                     lambda: run_setting(sc, s))
        err = distance(res, ref, sc.periodic_length or None)
        print(f"grid {s.scheme:5s} p = {s.p:2d} E/T = {s.tol:<6g}: error {err:.3g}, {res['cpu']:.3g} s CPU, "
              f"{res['solves']} solves")
    return 0


def _scene_and_rest(argv):
    path, rest = argv[0], argv[1:]
    getter = optmod.argv_getter(rest)
    return optmod.apply_overrides(scenemod.load_scene(path), getter)


def table(out, log=print):
    """Markdown: each verify run of OUT against its prediction and the fastest grid setting
    (OUT/grid, and for the study's scene its cached cases) that reached the same error."""
    log("| scene | E | plan | error (x E) | predicted | CPU s (x predicted) | predicted | fastest grid setting "
        "reaching E: CPU s | grid / plan |\n|---|---|---|---|---|---|---|---|---|")
    def order(p):
        head, tail = os.path.basename(p)[:-5].split("_E")
        return head, "_pilot" in tail, -float(tail.split("_pilot")[0])
    for path in sorted(glob.glob(os.path.join(out, "verify_*.json")), key=order):
        with open(path) as f:
            v = json.load(f)
        with open(v["ref"]) as f:
            ref = json.load(f)
        sc = scenemod.load_scene(v["scene"])
        period = sc.periodic_length or None
        stem = os.path.basename(path)[len("verify_"):].split("_E")[0]
        grid_runs = []
        for g in glob.glob(os.path.join(out, "grid", f"{stem}_*.json")):
            with open(g) as f:
                r = json.load(f)
            o = r["setting"]
            grid_runs.append((f"{o['-ts_type']} p{o['-ves_p']} {o['-ves_adapt_tol']:g}", r["cpu"],
                              distance(r, ref, period), "now"))
        if v["ref"].endswith(f"{REFERENCE.key}.json"):            # the study's own cases
            _, cases = study_cases()
            have = {x[0] for x in grid_runs}
            for r in cases:
                name = f"{r['scheme']} p{r['p']} {r['tol']:g}"
                if name not in have and r["R"] == 0:
                    grid_runs.append((name, r["cpu"], study.position_error(r, ref), "study"))
        reach = [x for x in grid_runs if x[2] is not None and x[2] <= v["target"]]
        best = min(reach, key=lambda x: x[1]) if reach else None
        o = v["setting"]
        log(f"| {stem} | {v['target']:g} | {o['-ts_type']} p{o['-ves_p']} E/T {o['-ves_adapt_tol']:g}"
            + (f" far {o['-ves_far_tol']:g}" if "-ves_far_tol" in o else "") + (f" (pilots to {path.split('_pilot')[1][:-5]} T)" if "_pilot" in path else "")
            + f" | {v['error']:.2e} ({v['error'] / v['target']:.2f}) | {v['predicted_error']:.2e} | {v['cpu']:.1f} "
            f"({v['cpu'] / v['predicted_seconds']:.2f}) | {v['predicted_seconds']:.1f} | "
            + (f"{best[0]}: {best[1]:.1f} ({best[3]}) | {best[1] / v['cpu']:.2f} |" if best else
               f"none of {len(grid_runs)} | - |"))


def main(argv):
    if argv and argv[0] == "table":
        table(argv[1] if len(argv) > 1 else "docs/study/plan")
        return 0
    if not argv or argv[0] not in ("fit", "reference", "verify", "grid"):
        print(__doc__)
        return 2
    cmd, rest = argv[0], argv[1:]
    if cmd == "fit":
        dirs = tuple(rest) or STUDY_DIRS
        fit = fit_from_study(dirs)
        print(json.dumps(fit, indent=1))
        in_sample(fit, dirs)
        return 0
    flags = {}
    args = []
    k = 0
    while k < len(rest):
        if rest[k] in ("--out", "--ref", "--error", "--pilot", "--only"):
            flags[rest[k]] = rest[k + 1]
            k += 2
        else:
            args.append(rest[k])
            k += 1
    sc = _scene_and_rest(args)
    if cmd == "reference":
        out = flags.get("--out", "out/plan")
        s = planner.Setting(REFERENCE.scheme, REFERENCE.p, REFERENCE.tol, 2 * REFERENCE.p, 2 * REFERENCE.p,
                            sc.repulsion.radius if sc.repulsion is not None else 0.0)
        path = os.path.join(out, f"reference_{os.path.basename(args[0]).split('.')[0]}_T{sc.time.horizon:g}.json")
        res = cached(path, lambda: run_setting(sc, s))
        print(f"reference {path}: {res['status']}, {res['solves']} solves, {res['cpu']:.1f} s CPU")
        return 0
    with open(flags["--ref"]) as f:
        ref = json.load(f)
    if cmd == "grid":
        return grid(sc, args[0], ref, flags["--out"], flags.get("--only"))
    E = float(flags["--error"])
    pl = planner.Planner(sc)
    if "--pilot" in flags:
        pl.model = calibrate(sc, pl, float(flags["--pilot"]), cache_dir=flags.get("--out"))
    best, runner = pl.plan(error=E)
    print(f"plan     {best.line()}")
    res = run_setting(sc, best.setting)
    err = distance(res, ref, sc.periodic_length or None)
    print(f"measured error {err:.3g} ({err / E:.2f} E), {res['cpu']:.3g} s CPU ({res['cpu'] / best.seconds:.2f} of "
          f"the predicted), {res['solves']} solves (predicted {best.solves:.0f}); status {res['status']}")
    out = flags.get("--out")
    if out:
        os.makedirs(out, exist_ok=True)
        pilot = f"_pilot{float(flags['--pilot']):g}" if "--pilot" in flags else ""
        name = f"verify_{os.path.basename(args[0]).split('.')[0]}_T{sc.time.horizon:g}_E{E:g}{pilot}.json"
        with open(os.path.join(out, name), "w") as f:
            json.dump(dict(res, error=err, target=E, scene=args[0], ref=flags["--ref"], predicted_error=best.error, predicted_seconds=best.seconds,
                           predicted_solves=best.solves, pilot=pl.model.pilot), f)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

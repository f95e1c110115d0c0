"""`vesflow plan SCENE.toml --error E [--budget SECONDS] [--pilot [FRACTION]]`: the command line
of the planner (vesflow.planner: models and search; vesflow.plan_fit: the pilot runs that
calibrate the models on the scene; docs/howto/plan.md)."""
from __future__ import annotations

import math
import shlex
import sys

from . import options as optmod, scene as scenemod
from .errors import SceneError
from .plan_fit import calibrate
from .planner import Planner, fixed_from_options


USAGE = ("usage: vesflow plan SCENE.toml --error E [--budget SECONDS] [--pilot [FRACTION]] [-ves_ / -ts_ options "
         "that fix a setting: -ves_p, -ts_type, -ves_adapt_tol, -ves_repulsion_radius]")


def _parse(argv):
    if not argv or argv[0].startswith("-"):
        raise SceneError(USAGE)
    path, rest, vals, k = argv[0], [], {"--error": None, "--budget": None, "--pilot": None}, 1
    while k < len(argv):
        a = argv[k]
        if a in ("--error", "--budget"):
            if k + 1 >= len(argv):
                raise SceneError(f"{a} needs a value")
            try:
                v = float(argv[k + 1])
                if not (v > 0 and math.isfinite(v)) or (a == "--error" and v >= 1):
                    raise ValueError
            except ValueError:
                rng = "a number in (0, 1)" if a == "--error" else "a number of seconds > 0"
                raise SceneError(f"{a} {argv[k + 1]}: must be {rng}") from None
            vals[a] = v
            k += 2
        elif a == "--pilot":
            frac = 1.0
            if k + 1 < len(argv) and not argv[k + 1].startswith("-"):
                try:
                    frac = float(argv[k + 1])
                    if not 0 < frac <= 1:
                        raise ValueError
                except ValueError:
                    raise SceneError(f"--pilot {argv[k + 1]}: the fraction of the horizon must be in (0, 1]") from None
                k += 1
            vals["--pilot"] = frac
            k += 1
        else:
            rest.append(a)
            k += 1
    return path, vals, rest


def main(argv):
    """`vesflow plan ...` (returns the exit status)."""
    if argv and argv[0] in ("-h", "--help", "-help"):
        print(USAGE)
        return 0
    path, vals, rest = _parse(argv)
    optmod.check_unknown([a for a in rest if a.startswith("-ves_")])
    getter = optmod.argv_getter(rest)
    sc = optmod.apply_overrides(scenemod.load_scene(path), getter)
    error = vals["--error"] if vals["--error"] is not None else (sc.accuracy.error if sc.accuracy else None)
    pl = Planner(sc, fixed=fixed_from_options(getter))
    if vals["--pilot"] is not None:
        pl.model = calibrate(sc, pl, vals["--pilot"], log=print)
    best, runner = pl.plan(error=error, budget=vals["--budget"])
    goal = (f"error {error:g}" if error is not None else "") + (" within " if error and vals["--budget"] else "") + \
        (f"budget {vals['--budget']:g} s" if vals["--budget"] else "")
    print(f"plan     {sc.title!r} ({path}), T = {sc.time.horizon:g}, {sc.n_vesicles} vesicles: {goal}")
    print(f"chosen   {best.line()}")
    print(f"runner-up {runner.line()}" if runner is not None else "runner-up none")
    print(f"command  vesflow run {shlex.quote(path)} {shlex.join(best.setting.argv() + rest)}")
    print(f"model    {pl.model.fit['source']}; " + (pl.model.pilot or "no pilot runs (--pilot calibrates the model "
                                                                       "on this scene)"))
    print(f"         errors are against a p = {pl.model.fit['p_ref']} solution, itself ~"
          f"{pl.model.reference_error(sc.time.horizon):.1g} from the converged one by the spatial fit")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""`vesflow run | check | render` (INTERFACE.md).  Exit status: 0 done, 2 bad input, 3 numerical failure."""
from __future__ import annotations

import os
import sys

from .errors import SceneError, VesflowError

USAGE = """usage: vesflow run [SCENE.toml] [-o OUT.h5] [--restart OUT.h5] [PETSc and -ves_ options ...]
       vesflow check SCENE.toml
       vesflow render OUT.h5|OUT.pvd [-o movie.mp4] [--frames DIR] [--color tension|speed|none]
       vesflow run -help          every vesflow option with its default"""


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        return 0 if argv else 2
    cmd, rest = argv[0], argv[1:]
    try:
        if cmd == "run":
            return cmd_run(rest)
        if cmd == "check":
            return cmd_check(rest)
        if cmd == "render":
            from .render import main as render_main
            return render_main(rest, prog="vesflow render")
        raise SceneError(f"unknown command {cmd!r}: use run, check or render")
    except SceneError as e:
        print(f"vesflow: error: {e}", file=sys.stderr)
        return 2
    except VesflowError as e:
        print(f"vesflow: {type(e).__name__}: {e}", file=sys.stderr)
        return e.exit_status


def _split_run_args(rest):
    """[SCENE] first (if not an option), then -o / --restart anywhere; the rest goes to PETSc."""
    scene_path, out, restart, petsc = None, None, None, []
    if rest and not rest[0].startswith("-"):
        scene_path, rest = rest[0], rest[1:]
    k = 0
    while k < len(rest):
        a = rest[k]
        if a in ("-o", "--output", "--restart"):
            if k + 1 >= len(rest):
                raise SceneError(f"{a} needs a file name")
            if a == "--restart":
                restart = rest[k + 1]
            else:
                out = rest[k + 1]
            k += 2
            continue
        petsc.append(a)
        k += 1
    return scene_path, out, restart, petsc


def cmd_check(rest):
    from . import scene as scenemod
    from .costs import estimate
    if len(rest) != 1:
        raise SceneError("usage: vesflow check SCENE.toml")
    sc = scenemod.load_scene(rest[0])
    print(sc.summary())
    print(estimate(sc))
    return 0


def cmd_run(rest):
    from . import options, scene as scenemod
    if any(a in ("-help", "--help", "-h") for a in rest):
        print(USAGE + "\n")
        print(options.help_text())
        return 0
    scene_path, out, restart, petsc_args = _split_run_args(rest)
    # validate our own options before PETSc starts (one-line errors, exit 2)
    getter = options.argv_getter(petsc_args)
    options.check_unknown([a for a in petsc_args if a.startswith("-ves_")])
    if restart is not None:
        from .io import read_checkpoint, read_output
        prev = read_output(restart)
        sc = scenemod.parse_scene(prev.attrs["scene"], source=restart)
        checkpoint = read_checkpoint(restart)
    else:
        sc = scenemod.load_scene(scene_path) if scene_path else scenemod.default_scene()
        checkpoint = None
    sc = options.apply_overrides(sc, getter)
    opts = options.read_options(getter, sc)
    import petsc4py
    petsc4py.init([sys.argv[0]] + petsc_args)
    from petsc4py import PETSc
    db = PETSc.Options()
    for a in petsc_args:                     # our own options are read above: mark them used for -options_left
        if a.startswith(("-ves_", "-ts_")) and db.hasName(a[1:]):
            db.getString(a[1:], "")
    from .io import OutputWriter
    from .simulation import Run
    out = restart or out or sc.output.file
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    options_text = " ".join(petsc_args)
    if restart is not None:
        writer = OutputWriter.reopen(restart, options_text=options_text)
    else:
        from . import __version__
        writer = OutputWriter(out, scene_text=sc.text or scenemod.DEFAULT_SCENE_TEXT, options_text=options_text,
                              version=__version__, p=sc.p, n_vesicles=sc.n_vesicles,
                              periodic_length=sc.periodic_length)
    progress = opts["progress"] == "on" or (opts["progress"] == "auto" and sys.stderr.isatty())
    rank0 = PETSc.COMM_WORLD.getRank() == 0
    if rank0:
        print(f"vesflow: {sc.title}: {sc.n_vesicles} vesicles, p = {sc.p}, T = {sc.time.horizon:g} -> {out}"
              + (" (restart)" if restart else ""))
    try:
        run = Run(sc, opts, writer=writer, checkpoint=checkpoint, progress=progress and rank0,
                  monitor=opts["ts_monitor"] and rank0)
        run.run()
    finally:
        writer.close()
    if rank0:
        tm = run.timers.as_dict()
        print(f"vesflow: done at t = {run.t:g}: {run.counts['accepted']} accepted, {run.counts['rejected']} "
              f"rejected steps; time {tm['total']:.1f} s (setup {tm['setup']:.1f}, self {tm['self']:.1f}, "
              f"near {tm['near']:.1f}, far {tm['far']:.1f}, repar {tm['repar']:.1f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""`vesflow run | check | render` (INTERFACE.md).  Exit status: 0 done, 2 bad input, 3 numerical failure."""
from __future__ import annotations

import os
import shlex
import sys

from .errors import NumericalFailure, OptionError, SceneError, VesflowError

USAGE = """usage: vesflow run [SCENE.toml] [-o OUT.h5] [--restart OUT.h5] [PETSc and -ves_ options ...]
       vesflow check SCENE.toml [-ves_ options]
       vesflow render OUT.h5|OUT.pvd [-o movie.mp4] [--frames DIR] [--color tension|speed|none] [--camera follow|fit|fixed]
       vesflow study accuracy-cost [SCENE.toml] [--quick] [--out DIR]   the paper's Table 3 experiment
       vesflow run -help          every vesflow option with its default"""


_QUIET = False          # ranks other than 0 print no error messages


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
        if cmd == "study":
            from .study import main as study_main
            return study_main(rest)
        if cmd == "render":
            from .render import main as render_main
            return render_main(rest, prog="vesflow render")
        raise SceneError(f"unknown command {cmd!r}: use run, check, render or study")
    except SceneError as e:
        if not _QUIET:
            print(f"vesflow: error: {e}", file=sys.stderr)
        return 2
    except VesflowError as e:
        if not _QUIET:
            print(f"vesflow: {type(e).__name__}: {e}", file=sys.stderr)
        return e.exit_status
    except KeyboardInterrupt:
        print("\nvesflow: interrupted; continue from the last checkpoint with vesflow run --restart FILE",
              file=sys.stderr)
        return 130


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


def expand_options_files(args, _depth=0):
    """Replace every `-options_file FILE` by the options in FILE, in place (PETSc's order:
    later options override earlier ones, so the command line after it wins).  The file is
    PETSc's format: options and values separated by blanks, `#` starts a comment.  A missing
    file, a line that does not start with an option or an unknown -ves_ option in it is a
    SceneError naming the file and line."""
    from . import options
    out, k = [], 0
    while k < len(args):
        a = args[k]
        if a != "-options_file":
            out.append(a)
            k += 1
            continue
        if k + 1 >= len(args) or args[k + 1].startswith("-"):
            raise SceneError("-options_file needs a file name")
        path = args[k + 1]
        k += 2
        if _depth > 8:
            raise SceneError(f"-options_file {path}: options files nested more than 8 deep")
        try:
            with open(path, encoding="utf-8") as fh:
                text = fh.read()
        except (OSError, UnicodeDecodeError) as e:
            raise SceneError(f"-options_file {path}: cannot read it ({getattr(e, 'strerror', None) or e})") from None
        tokens = []
        for n, line in enumerate(text.splitlines(), 1):
            try:
                toks = shlex.split(line, comments=True)
            except ValueError as e:
                raise SceneError(f"{path}:{n}: {e}") from None
            if not toks:
                continue
            if not toks[0].startswith("-"):
                raise SceneError(f"{path}:{n}: expected an option (-name [value]), got {toks[0]!r}")
            try:
                options.check_unknown([t for t in toks if t.startswith("-ves_")])
            except OptionError as e:
                raise OptionError(f"{path}:{n}: {e}") from None
            tokens += toks
        out += expand_options_files(tokens, _depth + 1)
    return out


def cmd_check(rest):
    """Validate a scene (with the -ves_ / -ts_ options of a run applied) and print its effects
    and the cost estimate."""
    from . import options, scene as scenemod
    from .costs import estimate
    if not rest or rest[0].startswith("-"):
        raise SceneError("usage: vesflow check SCENE.toml [-ves_ options]")
    args = expand_options_files(rest[1:])
    options.check_unknown([a for a in args if a.startswith("-ves_")])
    getter = options.argv_getter(args)
    sc = options.apply_overrides(scenemod.load_scene(rest[0]), getter)
    opts = options.read_options(getter, sc)
    print(sc.summary())
    print(estimate(sc, opts))
    return 0


def cmd_run(rest):
    from . import options, scene as scenemod
    if any(a in ("-help", "--help", "-h") for a in rest):
        print(USAGE + "\n")
        print(options.help_text())
        return 0
    scene_path, out, restart, cmdline = _split_run_args(rest)
    # validate our own options before PETSc starts (one-line errors, exit 2)
    cmdline = expand_options_files(cmdline)
    options.check_unknown([a for a in cmdline if a.startswith("-ves_")])
    checkpoint = None
    if restart is not None:
        from .io import read_attributes, read_checkpoint
        if scene_path is not None:
            raise SceneError(f"give a scene or --restart, not both: the scene of {restart} is stored in it")
        prev = read_attributes(restart, what="--restart")
        checkpoint = read_checkpoint(restart)
        sc = scenemod.parse_scene(prev["scene"], source=restart)
        # the options of the interrupted run and of its earlier restarts first, then the new
        # ones (later ones win)
        petsc_args = shlex.split(str(prev.get("options", "")))
        for earlier in prev.get("restart_options", []):
            petsc_args += shlex.split(str(earlier))
        petsc_args += cmdline
    else:
        sc = scenemod.load_scene(scene_path) if scene_path else scenemod.default_scene()
        petsc_args = cmdline
    getter = options.argv_getter(petsc_args)
    sc = options.apply_overrides(sc, getter)
    opts = options.read_options(getter, sc)
    if restart is not None and (sc.p != int(prev["p"]) or sc.n_vesicles != int(prev["n_vesicles"])):
        raise OptionError(f"-ves_p = {sc.p}: a restart keeps the p = {int(prev['p'])} of {restart}")
    import petsc4py
    petsc4py.init([sys.argv[0]] + petsc_args)
    from petsc4py import PETSc
    db = PETSc.Options()
    for a in petsc_args:                     # our own options are read above: mark them used for -options_left
        if a.startswith(("-ves_", "-ts_")) and db.hasName(a[1:]):
            db.getString(a[1:], "")
    if PETSc.COMM_WORLD.getSize() > 1:
        global _QUIET
        _QUIET = PETSc.COMM_WORLD.getRank() != 0
        raise SceneError(f"{PETSc.COMM_WORLD.getSize()} MPI processes: parallel runs are not available yet "
                         "(the vesicle partition is a later issue); run one process and use OMP_NUM_THREADS threads")
    from .io import OutputWriter
    from .simulation import Run, check_available
    check_available(sc, opts)                # before the output file exists
    ck_every = opts["checkpoint_every"]
    if restart is not None:
        out = out or restart
        if os.path.abspath(out) != os.path.abspath(restart):    # continue in a copy, keep the original
            import shutil
            os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
            shutil.copyfile(restart, out)
        writer = OutputWriter.reopen(out, options_text=shlex.join(cmdline), checkpoint_every=ck_every,
                                     restart_of=restart)
        checkpoint = writer.checkpoint
    else:
        from . import __version__
        out = out or sc.output.file
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        writer = OutputWriter(out, scene_text=sc.text or scenemod.DEFAULT_SCENE_TEXT,
                              options_text=shlex.join(petsc_args), version=__version__, p=sc.p,
                              n_vesicles=sc.n_vesicles, periodic_length=sc.periodic_length,
                              checkpoint_every=ck_every)
        writer.write_attrs(options_resolved=shlex.join(opts.as_argv()))
    progress = opts["progress"] == "on" or (opts["progress"] == "auto" and sys.stderr.isatty())
    rank0 = PETSc.COMM_WORLD.getRank() == 0
    if rank0:
        print(f"vesflow: {sc.title}: {sc.n_vesicles} vesicles, p = {sc.p}, T = {sc.time.horizon:g} -> {out}"
              + (f" (restart from t = {float(checkpoint['time']):g})" if restart else ""))
    run = None
    try:
        run = Run(sc, opts, writer=writer, checkpoint=checkpoint, progress=progress and rank0,
                  monitor=opts["ts_monitor"] and rank0)
        # Determinism of restarts: the block preconditioner reuses LU factors across solves
        # (-ves_pc_lag); a restarted run starts without them.  Dropping them at every checkpoint
        # makes the uninterrupted run take exactly the steps a restart from that checkpoint takes.
        writer.on_checkpoint.append(lambda state: _reset_preconditioner(run.stepper))
        run.run()
        if writer.last_checkpoint_time is None or writer.last_checkpoint_time != run.t:
            writer.write_checkpoint(run.checkpoint(), force=True)     # the final state (e.g. -ts_max_steps)
    except NumericalFailure:
        # the last accepted state (also under -ves_checkpoint_every): continue it with other options
        if run is not None and writer.last_checkpoint_time != run.t:
            writer.write_checkpoint(run.checkpoint(), force=True)
        raise
    finally:
        writer.close()
    if rank0:
        tm = run.timers.as_dict()
        print(f"vesflow: done at t = {run.t:g}: {run.counts['accepted']} accepted, {run.counts['rejected']} "
              f"rejected steps; time {tm['total']:.1f} s (setup {tm['setup']:.1f}, self {tm['self']:.1f}, "
              f"near {tm['near']:.1f}, far {tm['far']:.1f}, repar {tm['repar']:.1f})")
    return 0


def _reset_preconditioner(stepper):
    """Forget the preconditioner's lagged LU factors (they are rebuilt at the next solve)."""
    reset = getattr(stepper, "reset_preconditioner", None)
    if reset is not None:
        reset()
    else:
        stepper._pc_context = None


if __name__ == "__main__":
    sys.exit(main())

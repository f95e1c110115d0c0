"""`vesflow run | check | render | export | study` (docs/reference/cli.md).  Exit status
(docs/reference/exit_status.md): 0 done, 2 bad input (also: the output file is in use by another
process), 3 numerical failure or a failed write of the output file, 128 + N stopped by signal N
(SIGTERM 143, SIGINT 130, SIGUSR1 138) at a step boundary with a checkpoint."""
from __future__ import annotations

import importlib
import json
import os
import shlex
import sys
import time
import traceback

from . import __version__, options, threads
from .errors import NumericalFailure, OptionError, OutputError, RunError, SceneError, SettingsError, VesflowError
from .signals import StopRequest, exit_status, signal_name
from .solver import check_options, error_reason

USAGE = """usage: vesflow run [SCENE.toml] [-o OUT.h5] [--restart OUT.h5] [PETSc and -ves_ options ...]
       vesflow check SCENE.toml [-ves_ and PETSc options]
       vesflow render OUT.h5|OUT.pvd [-o movie.mp4] [--frames DIR] [--color tension|speed|none] [--camera follow|fit|fixed]
       vesflow export OUT.h5 [--vtk DIR]   OUT.xmf beside it (ParaView, VisIt); --vtk: .vtp files and a .pvd
       vesflow study accuracy-cost [SCENE.toml] [--quick] [--out DIR]   the paper's Table 3 experiment
       vesflow plan SCENE.toml --error E [--budget SECONDS] [--pilot [FRACTION]]   the cheapest settings for E
       vesflow run -help          every vesflow option with its default
       mpiexec -n N vesflow run ...   the vesicles divided among N ranks (docs/explanation/parallel.md)"""


_QUIET = False          # ranks other than 0 print no error messages
_T_MAIN = None          # when main() started: the time to the first step is printed from it


def main(argv=None):
    global _T_MAIN, _QUIET
    _T_MAIN = time.perf_counter()
    _QUIET = _launcher_rank() not in (None, 0)   # errors before MPI starts: rank 0 prints them
    threads.early_environment()              # before numpy is loaded (vesflow.threads)
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
            threads.configure()                  # the runs' thread policy (vesflow.threads)
            from .study import main as study_main  # lazy: numpy is loaded after threads.early_environment() (main)
            return study_main(rest)
        if cmd == "plan":
            threads.configure()                  # pilot runs (--pilot): the runs' thread policy
            from .plan_command import main as plan_main  # lazy: numpy is loaded after threads.early_environment() (main)
            return plan_main(rest)
        if cmd == "render":
            require_packages("vesflow render", RENDER_PACKAGES, "render")
            from .render import main as render_main  # lazy: numpy is loaded after threads.early_environment() (main)
            return render_main(rest, prog="vesflow render")
        if cmd == "export":
            return cmd_export(rest)
        raise SceneError(f"unknown command {cmd!r}: use run, check, plan, render, export or study")
    except (SceneError, SettingsError) as e:
        _quiet_petsc_exit()
        if not _QUIET:
            print(f"vesflow: error: {e}", file=sys.stderr)
        return 2
    except VesflowError as e:
        _quiet_petsc_exit()
        if not _QUIET:
            print(f"vesflow: {type(e).__name__}: {e}", file=sys.stderr)
        return e.exit_status
    except KeyboardInterrupt:
        _quiet_petsc_exit()
        if not _QUIET:
            print("\nvesflow: interrupted; continue from the last checkpoint with vesflow run --restart FILE",
                  file=sys.stderr)
        return 130
    except Exception as e:                  # a bug outside a run's steps: one line too
        _quiet_petsc_exit()
        if _wants_traceback(rest):
            traceback.print_exc()
        if not _QUIET:
            print(f"vesflow: unexpected error: {error_reason(e)} (-ves_traceback shows the full trace)",
                  file=sys.stderr)
        return 3


# module -> distribution of the packages `vesflow render` needs (pyproject.toml's render extra)
RENDER_PACKAGES = {"pyvista": "pyvista", "imageio_ffmpeg": "imageio-ffmpeg", "PIL": "pillow"}


def require_packages(what, packages, extra):
    """SceneError naming the packages of `packages` (module -> distribution) that do not
    import, before any work."""
    missing = []
    for module, dist in packages.items():
        try:
            importlib.import_module(module)
        except ImportError:
            missing.append(dist)
    if missing:
        raise SceneError(f"{what} needs the Python package{'s' if len(missing) > 1 else ''} "
                         f"{', '.join(missing)}: pip install {' '.join(missing)} (or vesflow[{extra}])")


def _launcher_rank():
    """This process's rank as mpiexec / srun set it in the environment (None: not launched so)."""
    for name in ("PMI_RANK", "OMPI_COMM_WORLD_RANK", "PMIX_RANK"):
        if os.environ.get(name, "").isdigit():
            return int(os.environ[name])
    return None


def _wants_traceback(args):
    raw = options.argv_getter(args)("-ves_traceback", bool, False)
    try:
        return raw is not None and options.parse_value("-ves_traceback", raw)
    except VesflowError:
        return False


def _quiet_petsc_exit():
    """After an error, PETSc's exit report of unused options (most are unread because the run
    stopped) would follow the one-line message: switch it off."""
    PETSc = sys.modules.get("petsc4py.PETSc")
    if PETSc is not None and PETSc.Sys.isInitialized():
        PETSc.Options().setValue("-options_left", "0")


def _split_run_args(rest):
    """[SCENE] first (if not an option), then -o / --restart anywhere; the rest goes to PETSc."""
    scene_path, out, restart = None, None, None
    if rest and not rest[0].startswith("-"):
        scene_path, rest = rest[0], rest[1:]
    pairs, petsc = options.take_valued(rest, ("-o", "--output", "--restart"), "a file name")
    for name, value in pairs:
        if name == "--restart":
            restart = value
        else:
            out = value
    return scene_path, out, restart, petsc


def expand_options_files(args, origins=None):
    """Replace every `-options_file FILE` by the options in FILE, in place (PETSc's order:
    later options override earlier ones, so the command line after it wins).  The file is
    PETSc's format: options and values separated by blanks, `#` starts a comment.  A missing
    file, a line that does not start with an option or an unknown -ves_ option in it is a
    SceneError naming the file and line.  origins: a list, filled with where each returned
    token came from ("FILE:LINE", None for the command line)."""
    out, where = _expand(list(args), [None] * len(args), 0)
    if origins is not None:
        origins[:] = where
    return out


def _expand(args, where, depth):
    out, out_where, k = [], [], 0
    while k < len(args):
        a = args[k]
        if a != "-options_file":
            out.append(a)
            out_where.append(where[k])
            k += 1
            continue
        if k + 1 >= len(args) or args[k + 1].startswith("-"):
            raise SceneError("-options_file needs a file name")
        path = args[k + 1]
        k += 2
        if depth > 8:
            raise SceneError(f"-options_file {path}: options files nested more than 8 deep")
        try:
            with open(path, encoding="utf-8") as fh:
                text = fh.read()
        except (OSError, UnicodeDecodeError) as e:
            raise SceneError(f"-options_file {path}: cannot read it ({getattr(e, 'strerror', None) or e})") from None
        tokens, token_where = [], []
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
            token_where += [f"{path}:{n}"] * len(toks)
        sub, sub_where = _expand(tokens, token_where, depth + 1)
        out += sub
        out_where += sub_where
    return out, out_where


def cmd_check(rest):
    """Validate a scene (with the -ves_ / -ts_ options of a run applied) and PETSc's options, and
    print its effects and the cost estimate."""
    from . import scene as scenemod  # lazy: numpy is loaded after threads.early_environment() (main)
    from .costs import estimate  # lazy: numpy is loaded after threads.early_environment() (main)
    if not rest or rest[0].startswith("-"):
        raise SceneError("usage: vesflow check SCENE.toml [-ves_ options]")
    origins = []
    args = expand_options_files(rest[1:], origins)
    options.check_unknown([a for a in args if a.startswith("-ves_")])
    getter = options.argv_getter(args)
    sc = options.apply_overrides(scenemod.load_scene(rest[0]), getter)
    opts = options.read_options(getter, sc)
    if any(name not in options.OPTIONS for _, name, _ in options.argv_pairs(args)):   # PETSc's options
        _init_petsc(args)
        check_options(args, origins=origins)
    print(sc.summary())
    from .costs import fit_memory  # lazy: numpy is loaded after threads.early_environment() (main)
    est = estimate(sc, opts)
    try:
        fitted, line = fit_memory(sc, opts, est=est)
    except NumericalFailure as e:      # check reports what a run would refuse, and exits 0
        fitted, line = opts, f"refused  {e}"
    print(est if fitted is opts else estimate(sc, fitted))
    if line:
        print(line if line.startswith("refused") else f"choices  {line}")
    return 0


def cmd_export(rest):
    """vesflow export RUN.h5 [--vtk DIR]: write RUN.xmf beside RUN.h5 (its frames for ParaView
    and VisIt, read from RUN.h5: vesflow.io.xdmf); with --vtk also DIR/RUN_*.vtp and DIR/RUN.pvd."""
    import argparse
    from .io.xdmf import write_xdmf  # lazy: numpy is loaded after threads.early_environment() (main)
    ap = argparse.ArgumentParser(prog="vesflow export", description=cmd_export.__doc__)
    ap.add_argument("run", help="run file (.h5)")
    ap.add_argument("--vtk", metavar="DIR", default=None, help="also write the frames as .vtp files and a .pvd in DIR")
    args = ap.parse_args(rest)
    from .io import read_attributes  # lazy: numpy is loaded after threads.early_environment() (main)
    read_attributes(args.run, what="vesflow export")       # a missing file, or not a run file: one line
    if args.vtk is not None:
        require_packages("vesflow export --vtk", {"pyvista": "pyvista"}, "render")
    print(write_xdmf(args.run))
    if args.vtk is not None:
        from .vtk_export import export_vtk  # lazy: pyvista, only for --vtk
        print(export_vtk(args.run, args.vtk))
    return 0


def cmd_run(rest):
    """`vesflow run`: SIGTERM, SIGINT and SIGUSR1 stop it at the next step boundary
    (vesflow.signals), from the start (the handlers are installed before PETSc, which is
    started with -no_signal_handler)."""
    if any(a in ("-help", "--help", "-h") for a in rest):
        print(USAGE + "\n")
        print(options.help_text())
        return 0
    stop = StopRequest().install()
    try:
        return _run(rest, stop)
    finally:
        stop.restore()


def _run(rest, stop):
    from . import scene as scenemod  # lazy: numpy is loaded after threads.early_environment() (main)
    scene_path, out, restart, cmdline = _split_run_args(rest)
    # validate our own options before PETSc starts (one-line errors, exit 2)
    cmd_origins = []
    cmdline = expand_options_files(cmdline, cmd_origins)
    options.check_unknown([a for a in cmdline if a.startswith("-ves_")])
    checkpoint = None
    if restart is not None:
        from .io import read_attributes, read_checkpoint  # lazy: numpy is loaded after threads.early_environment() (main)
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
        origins = [f"the options stored in {restart}"] * len(petsc_args) + cmd_origins
        petsc_args += cmdline
    else:
        sc = scenemod.load_scene(scene_path) if scene_path else scenemod.default_scene()
        petsc_args, origins = cmdline, cmd_origins
    plan = None
    if restart is None and sc.accuracy is not None:      # [accuracy]: the planner's options first (ours win)
        from .planner import plan_for_run  # lazy: numpy is loaded after threads.early_environment() (main)
        plan_args, plan_line, plan = plan_for_run(sc, petsc_args)
        petsc_args, origins = plan_args + petsc_args, ["the plan for [accuracy]"] * len(plan_args) + origins
    getter = options.argv_getter(petsc_args)
    sc = options.apply_overrides(sc, getter)
    opts = options.read_options(getter, sc)
    threads.configure(opts["blas_threads"])   # before the compiled kernels are loaded
    if restart is not None and (sc.p != int(prev["p"]) or sc.n_vesicles != int(prev["n_vesicles"])):
        raise OptionError(f"-ves_p = {sc.p}: a restart keeps the p = {int(prev['p'])} of {restart}")
    PETSc = _init_petsc(petsc_args)
    size = PETSc.COMM_WORLD.getSize()
    rank0 = PETSc.COMM_WORLD.getRank() == 0
    if size > 1:          # vesicles over the ranks (vesflow.parallel); messages from rank 0
        global _QUIET
        _QUIET = not rank0
        if sc.wall is not None:
            raise SettingsError(f"[wall]: walls need one rank (this run has {size} MPI processes)")
        if size > sc.n_vesicles:
            raise SceneError(f"{size} MPI processes for {sc.n_vesicles} vesicles: each rank needs at least one "
                             f"vesicle; run at most {sc.n_vesicles} processes")
        PETSc.COMM_WORLD.barrier()      # every rank has read the --restart file before rank 0 opens it
    check_options(petsc_args, origins=origins)      # PETSc's options too, before the output file exists
    from .io import OutputWriter  # lazy: numpy is loaded after threads.early_environment() (main)
    from .simulation import Run, check_available  # lazy: numpy is loaded after threads.early_environment() (main)
    check_available(sc, opts)                # before the output file exists
    from .costs import fit_memory  # lazy: numpy is loaded after threads.early_environment() (main)
    opts, memory_line = fit_memory(sc, opts, ranks=size)      # refuses (one line) before any work
    if memory_line and rank0:
        print(f"vesflow: {memory_line}")
    ck_every = opts["checkpoint_every"]
    failure = None
    try:
        if not rank0:                            # rank 0 writes the one file
            from .io import PeerWriter  # lazy: numpy is loaded after threads.early_environment() (main)
            out = out or (restart if restart is not None else sc.output.file)
            writer = PeerWriter(ck_every, None if checkpoint is None else float(checkpoint["time"]))
        elif restart is not None:
            out = out or restart
            if os.path.abspath(out) != os.path.abspath(restart):    # continue in a copy, keep the original
                import shutil
                from .io.journal import FileInUse, check_not_in_use  # lazy: numpy is loaded after threads.early_environment() (main)
                try:
                    check_not_in_use(out)
                except FileInUse as e:
                    raise SceneError(e.strerror) from None
                os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
                shutil.copyfile(restart, out)
            writer = OutputWriter.reopen(out, options_text=shlex.join(cmdline), checkpoint_every=ck_every,
                                         restart_of=restart)
            checkpoint = writer.checkpoint
        else:
            out = out or sc.output.file
            os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
            writer = OutputWriter(out, scene_text=sc.text or scenemod.DEFAULT_SCENE_TEXT,
                                  options_text=shlex.join(petsc_args), version=__version__, p=sc.p,
                                  n_vesicles=sc.n_vesicles, periodic_length=sc.periodic_length,
                                  checkpoint_every=ck_every)
            from .costs import decision_rules, decisions  # lazy: numpy is loaded after threads.early_environment() (main)
            writer.write_attrs(options_resolved=shlex.join(opts.as_argv()), decision_rules=json.dumps(decision_rules()),
                               decisions=json.dumps(decisions(sc, opts)))
            if plan is not None:
                writer.write_attrs(plan=json.dumps(plan))
    except Exception as e:                   # rank 0 could not create / reopen the file
        failure = e
    comm = PETSc.COMM_WORLD.tompi4py() if size > 1 else None
    if comm is not None:     # every rank learns it (no rank left waiting), rank 0 reports it
        said = comm.bcast(None if failure is None else (str(failure), isinstance(failure, OutputError)), root=0)
        if said is not None and failure is None:
            raise (OutputError if said[1] else SceneError)(said[0])
    if failure is not None:
        raise failure
    # a failed write is kept by the writer and stops the run at the next step boundary on every
    # rank (the poll reduces it with the signals), then reported by rank 0
    writer.defer_errors = True
    stop.comm, stop.writer, stop.out = comm, writer, out
    progress = opts["progress"] == "on" or (opts["progress"] == "auto" and sys.stderr.isatty())
    if rank0 and plan is not None:
        print(plan_line)
    if rank0:
        print(f"vesflow: {sc.title}: {sc.n_vesicles} vesicles, p = {sc.p}, T = {sc.time.horizon:g} -> {out}"
              + (f" (restart from t = {float(checkpoint['time']):g})" if restart else ""))
    run = None
    try:
        run = Run(sc, opts, writer=writer, checkpoint=checkpoint, progress=progress and rank0,
                  monitor=opts["ts_monitor"] and rank0)
        run.stop = stop
        run.run()
        if writer.last_checkpoint_time is None or writer.last_checkpoint_time != run.t:
            writer.write_checkpoint(run.checkpoint(), force=True)     # the final state (e.g. -ts_max_steps, a signal)
    except NumericalFailure:
        # the last accepted state (also under -ves_checkpoint_every): continue it with other options
        if run is not None and writer.last_checkpoint_time != run.t:
            writer.write_checkpoint(run.checkpoint(), force=True)
        if getattr(writer, "failure", None) is not None:    # it could not be saved: say why
            raise writer.failure from None
        raise
    except (SceneError, SettingsError, OutputError):
        raise
    except Exception as e:                   # a PETSc error or a bug: one line, the last good state saved
        if opts["traceback"]:
            traceback.print_exc()
        err = _run_error(e, run, writer, out)
        if size > 1:         # possibly on this rank only: say so, and end every rank (no rank left waiting)
            print(f"vesflow: rank {PETSc.COMM_WORLD.getRank()}: {type(err).__name__}: {err}", file=sys.stderr)
            sys.stderr.flush()
            PETSc.COMM_WORLD.tompi4py().Abort(err.exit_status)
        raise err from e
    finally:
        writer.close()
    failed = getattr(writer, "failure", None) is not None
    if comm is not None:     # a write that failed after the last poll (the final checkpoint, the close)
        failed = bool(comm.allreduce(int(failed), op=_mpi_max()))
    if failed:
        _quiet_petsc_exit()
        if rank0:
            raise writer.failure
        return OutputError.exit_status
    if stop.signum:
        _quiet_petsc_exit()
        if rank0:
            print(f"vesflow: stopped by {signal_name(stop.signum)} at t = {run.t:.6g}, step {run.n_accepted}; "
                  f"checkpoint at t = {writer.last_checkpoint_time:.6g}; continue with --restart {out}",
                  file=sys.stderr)
        return exit_status(stop.signum)
    if rank0:
        tm = run.timers.as_dict()
        print(f"vesflow: done at t = {run.t:g}: {run.counts['accepted']} accepted, {run.counts['rejected']} "
              f"rejected steps; time {tm['total']:.1f} s (setup {tm['setup']:.1f}, self {tm['self']:.1f}, "
              f"near {tm['near']:.1f}, far {tm['far']:.1f}, repar {tm['repar']:.1f})"
              + (f"; {run.contacts.count} steps in contact separated (docs/explanation/contacts.md)"
                 if run.contacts is not None and run.contacts.count else "")
              + (f"; first step after {run.first_step_at - _T_MAIN:.2f} s (imports, shapes, caches)"
                 if run.first_step_at is not None and _T_MAIN is not None else ""))
    return 0


def _init_petsc(petsc_args):
    """Initialize PETSc with the options; vesflow's own (read above) are marked used, so that
    PETSc's report of unused options (-options_left, at exit) lists only misspelled ones."""
    import petsc4py
    # -no_signal_handler: PETSc's SIGTERM handler (an error block and MPI_Abort) would replace
    # vesflow's (vesflow.signals, installed before PETSc starts)
    petsc4py.init([sys.argv[0]] + petsc_args + ["-no_signal_handler"])
    from petsc4py import PETSc
    db = PETSc.Options()
    for _, name, _ in options.argv_pairs(petsc_args):
        if name in options.OPTIONS and db.hasName(name[1:]):
            db.getString(name[1:], "")
    return PETSc


def _run_error(e, run, writer, out):
    """RunError for an unexpected exception e during a run: where, why, and the last good state
    saved (or why it could not be)."""
    if getattr(writer, "failure", None) is not None:
        return writer.failure
    if run is None:
        return RunError(f"setting up the run: {error_reason(e)}; nothing was computed "
                        "(-ves_traceback shows the full trace)")
    try:
        run.save_last_good_state()
        saved = f"the last good state (t = {run.t:.6g}) is saved in {out}: vesflow run --restart {out} continues it"
    except Exception as e2:
        last = writer.last_checkpoint_time
        saved = (f"the last good state could not be saved ({error_reason(e2)})"
                 + (f"; {out} has the checkpoint at t = {last:.6g}" if last is not None else ""))
    return RunError(f"{run.position()}: {error_reason(e)}; {saved} (-ves_traceback shows the full trace)")


def _mpi_max():
    from mpi4py import MPI       # only under MPI
    return MPI.MAX


if __name__ == "__main__":
    sys.exit(main())

"""The KSP of the step (docs/explanation/method.md, section 6; paper 3.6), configured from PETSc's options database.

`configure_ksp` is the one place that sets the solver up: GMRES, rtol 1e-8, at most 1000
iterations, nonzero initial guess, vesflow's block-Jacobi PC context unless -pc_type is given,
then every -ksp_* / -pc_* option.  `Stepper.solve` calls it for each solve.

`check_options` configures and sets up a KSP the same way on a 1 x 1 operator before a run
writes anything, so that a bad PETSc option (an unknown type, a non-number, a negative count,
a preconditioner that needs matrix entries) is an `OptionError` naming the option (exit
status 2) instead of a PETSc error inside the first solve.
"""
from __future__ import annotations

import difflib
import re
import sys

from .errors import OptionError
from .options import argv_pairs

RTOL, MAX_IT = 1e-8, 1000          # vesflow's defaults; -ksp_rtol / -ksp_max_it override them


def configure_ksp(ksp, A, prefix=None, default_pc=None, ksp_type="gmres"):
    """Give ksp the operator A and configure it: vesflow's defaults, then the options database
    under prefix.  default_pc() returns the PC python context used when -pc_type is not given.
    ksp_type: the default type (fgmres with a float32 preconditioner, -ves_pc_precision single:
    GMRES's left-preconditioned residual would stall at the float32 rounding of the PC)."""
    from petsc4py import PETSc
    if prefix:
        ksp.setOptionsPrefix(prefix)
    ksp.setOperators(A)
    ksp.setType(ksp_type)
    ksp.setTolerances(rtol=RTOL, max_it=MAX_IT)
    ksp.setInitialGuessNonzero(True)
    if default_pc is not None and not PETSc.Options(prefix).hasName("pc_type"):
        pc = ksp.getPC()
        pc.setType("python")
        pc.setPythonContext(default_pc())
    ksp.setFromOptions()
    return ksp


# ----------------------------------------------------------------------------------------
# The check before a run
# ----------------------------------------------------------------------------------------
class _Identity:
    """MatPython context of the 1 x 1 stand-in operator."""

    def mult(self, mat, x, y):
        x.copy(y)


class _StandInPC:
    """Stands for the block-Jacobi context in the check: it reads no options."""

    def apply(self, pc, x, y):
        x.copy(y)


def _configure_stand_in(prefix, complete=True):
    """Configure and set up a KSP as a run does, on a 1 x 1 identity, and apply its PC once (some
    PCs set up on first use); the error or None.  A python PC is configured (its module
    imported, its options read) but used as none: its setUp needs vesflow's operator.
    complete=False: a python PC without a context is not an error (yet).  An error after the
    options were read has `needs_entries` set: the PC needs matrix entries vesflow has not."""
    from petsc4py import PETSc
    A = PETSc.Mat().createPython([1, 1], _Identity(), comm=PETSc.COMM_SELF)
    ksp = PETSc.KSP().create(comm=PETSc.COMM_SELF)
    pc = x = y = None
    err = None
    try:
        A.setUp()
        configure_ksp(ksp, A, prefix, default_pc=_StandInPC)
        pc = ksp.getPC()
        if pc.getType() == "python":
            ctx = pc.getPythonContext()
            if complete and ctx is None:
                return OptionError("-pc_type python: needs -pc_python_type MODULE.CLASS "
                                   "(vesflow.precond.BlockJacobi or vesflow.precond.SphereSpectral)")
            if ctx is not None and not callable(getattr(ctx, "apply", None)):
                return OptionError(f"-pc_python_type {pc.getPythonType()}: not a preconditioner (no method "
                                   "apply(pc, x, y)); vesflow's are vesflow.precond.BlockJacobi and SphereSpectral")
            pc.setType("none")
        try:
            ksp.setUp()
            x, y = A.createVecs()
            x.set(1.0)
            pc.apply(x, y)
        except PETSc.Error as e:
            e.needs_entries = "PCSetUp" in str(e) or "PCApply" in str(e)
            raise
    except Exception as e:          # PETSc.Error, or a PC python module's ImportError ...
        err = e
    finally:
        # a PC whose set-up failed may fail again when destroyed (jacobi in PETSc 3.26): quietly
        PETSc.Sys.pushErrorHandler("return")
        try:
            for obj in (pc, ksp, x, y, A):
                if obj is not None:
                    try:
                        obj.destroy()
                    except PETSc.Error:
                        pass
            del obj, pc, ksp, x, y, A
        finally:
            PETSc.Sys.popErrorHandler()
    return err


def check_options(argv=(), prefix=None, origins=None):
    """Raise OptionError if the KSP of a run cannot be configured from the options database.

    argv: the PETSc options given (as on the command line); the option responsible is found by
    putting them back into the database one at a time, in order, until the configuration fails
    (with the earlier options it needs, e.g. -pc_type python for -pc_python_type).  origins,
    parallel to argv: where each token came from ("FILE:LINE") or None.  The database is left
    as it was."""
    err = _configure_stand_in(prefix)
    if err is None:
        return
    if isinstance(err, OptionError):
        raise err
    from petsc4py import PETSc
    pairs = [(i, name, value) for i, name, value in argv_pairs(argv) if not name.startswith("-ves_")]
    db = PETSc.Options()
    for _, name, _ in pairs:
        db.delValue(name)
    culprit, needed = None, []
    try:
        if _configure_stand_in(prefix, False) is None:   # else: PETSC_OPTIONS or .petscrc
            active = []
            for k, (_, name, value) in enumerate(pairs):
                db.setValue(name, value)
                active.append(k)
                e = _configure_stand_in(prefix, False)
                if e is not None:
                    culprit, err = k, e
                    break
            if culprit is not None:
                for k in active[:-1]:                    # the earlier options the failure needs
                    _, name, value = pairs[k]
                    db.delValue(name)
                    if _configure_stand_in(prefix, False) is None:
                        needed.append(k)
                    db.setValue(name, value)
    finally:
        for _, name, _ in pairs:
            db.delValue(name)
        for _, name, value in pairs:
            db.setValue(name, value)
    reason = error_reason(err)
    if culprit is None:
        raise OptionError(f"PETSc options (PETSC_OPTIONS, .petscrc or the command line): {reason}")
    shown = []
    for k in needed + [culprit]:
        i, name, value = pairs[k]
        where = origins[i] if origins is not None and i < len(origins) and origins[i] else None
        shown.append((f"{where}: " if where else "") + name + ("" if value is None else f" {value}"))
    msg = f"{', '.join(shown)}: {reason}{_suggestion(pairs[culprit][1], pairs[culprit][2], prefix)}"
    if getattr(err, "needs_entries", False):
        msg += ("; vesflow's operator is matrix-free: use a python PC (vesflow.precond.BlockJacobi, "
                "SphereSpectral) or -pc_type none")
    e = OptionError(msg)
    e.key = pairs[culprit][1]
    raise e


_LOCATION = re.compile(r"^\S+\(\) at \S+:\d+$")


def error_reason(err) -> str:
    """Why err happened, on one line: PETSc's innermost message for a PETSc.Error (the Python
    exception behind it for an error in a python context), else 'TypeName: message'."""
    PETSc = sys.modules.get("petsc4py.PETSc")          # not imported: not a PETSc error
    if PETSc is None:
        return f"{type(err).__name__}: {err}".splitlines()[0]
    cause = err.__cause__ if isinstance(err, PETSc.Error) and err.__cause__ is not None else err
    if not isinstance(cause, PETSc.Error):
        return f"{type(cause).__name__}: {cause}".splitlines()[0]
    lines = [ln.split("] ", 1)[-1].strip() for ln in str(err).splitlines()[1:]]
    msgs = [ln for ln in lines if ln and not _LOCATION.match(ln) and not ln.startswith("Unknown type. Check")]
    code = getattr(err, "ierr", None)
    return (msgs[-1] if msgs else "PETSc error") + (f" (PETSc error code {code})" if code is not None else "")


def _suggestion(name, value, prefix):
    """'; did you mean gmres?' for an unknown -ksp_type / -pc_type."""
    from petsc4py import PETSc
    short = name.lstrip("-")[len(prefix or ""):]
    kinds = {"ksp_type": PETSc.KSP.Type, "pc_type": PETSc.PC.Type}
    if short not in kinds or value is None:
        return ""
    known = sorted({v for k, v in vars(kinds[short]).items() if not k.startswith("_") and isinstance(v, str)})
    if value in known:
        return ""
    sugg = difflib.get_close_matches(value, known, n=1, cutoff=0.7)
    return f"; did you mean {sugg[0]}?" if sugg else ""

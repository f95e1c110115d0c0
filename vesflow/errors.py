"""The one exceptions module: every message says what was wrong, where, and what to do."""


class VesflowError(Exception):
    """Base of all vesflow errors."""

    exit_status = 1


class SceneError(VesflowError):
    """Bad input: a scene key, an option value.  The CLI prints it on one line and exits 2."""

    exit_status = 2


class OptionError(SceneError):
    """A bad command-line option value."""


class SettingsError(VesflowError):
    """A numerical setting the layer potentials cannot honour (a far-field backend, accuracy or
    period; a grid that does not fit the memory).  Raised below the scene layer, which knows no
    scene key; the CLI prints it on one line and exits 2, as a SceneError."""

    exit_status = 2


class ConvergenceError(VesflowError):
    """A KSP solve failed: carries PETSc's reason and the iteration count."""

    exit_status = 3

    def __init__(self, message, reason=None, iterations=None):
        super().__init__(message)
        self.reason = reason
        self.iterations = iterations


class CollisionError(VesflowError):
    """Surfaces touch or overlap and the step could not be recovered."""

    exit_status = 3


class NumericalFailure(VesflowError):
    """Unrecoverable numerical failure (NaN, dt below its minimum); last good state was saved."""

    exit_status = 3


class RunError(VesflowError):
    """An unexpected error during a run (a PETSc error, a bug): says where (step, time) and why;
    the last good state was saved.  Exit status 3."""

    exit_status = 3


class OutputError(VesflowError):
    """Writing the output file failed (no space left on device, an I/O error): names the file
    and the cause; the file was put back to its last complete frame and checkpoint.  Exit 3."""

    exit_status = 3

"""Stopping a run at a step boundary on SIGTERM, SIGINT or SIGUSR1 (docs/howto/cluster_runs.md).

The handlers only note the signal; the run polls `StopRequest.poll()` at each step boundary
(the top of the time loop, where the state is the last accepted one) and stops there, after
which `vesflow run` writes the checkpoint, prints one line and exits with 128 + the signal
number.  Under MPI the poll is a MAX reduction over the ranks of the signal (or of an output
failure of rank 0's writer): every rank stops at the same step boundary, whichever ranks the
signal reached.  A second signal while waiting for the boundary stops at once (the default
action of the signal: the file keeps its last complete frame and checkpoint, vesflow.io.journal).

PETSc installs its own handler for SIGTERM (a "PETSC ERROR ... Caught signal" block and
MPI_Abort) in PetscInitialize; `vesflow run` starts PETSc with -no_signal_handler, so the handlers
installed here before PETSc starts stay in force (measured: with PETSc's default the SIGTERM
handler set before petsc4py.init is replaced; PETSc.Sys.popSignalHandler() after it resets
SIGTERM to the default action, killing the process).
"""
from __future__ import annotations

import os
import signal
import sys

SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGUSR1)
OUTPUT_FAILED = 255      # the poll's code for a failed write of the output file (above any signal)


def exit_status(signum):
    """The exit status of a run stopped by signal signum: 128 + signum (SIGTERM 143, SIGINT 130,
    SIGUSR1 138), as a shell reports a process the signal ended."""
    return 128 + int(signum)


def signal_name(signum):
    return signal.Signals(signum).name


class StopRequest:
    """The flag the signal handlers set and the run loop polls.

    StopRequest(comm=None, writer=None): comm an mpi4py communicator (the poll is then
    collective: call it at the same point on every rank); writer: its `failure` (an output
    error kept with defer_errors) stops the run too.
    """

    def __init__(self, comm=None, writer=None):
        self.comm = comm if comm is not None and comm.Get_size() > 1 else None
        self.writer = writer
        self.received = 0        # the first signal this process received
        self.code = 0            # what the ranks agreed on at the poll that stopped the run
        self.out = None          # the output file (for the line of a second signal)
        self._previous = None

    def install(self):
        """Handle SIGNALS (main thread only); restore() puts the previous handlers back."""
        self._previous = {s: signal.signal(s, self._handle) for s in SIGNALS}
        return self

    def restore(self):
        if self._previous:
            for s, h in self._previous.items():
                signal.signal(s, h if h is not None else signal.SIG_DFL)
        self._previous = None

    def _handle(self, signum, frame):
        if not self.received:
            self.received = signum
            return
        # a second signal: stop now, by the signal's default action
        sys.stderr.write(f"\nvesflow: second {signal_name(signum)}: stopped at once; "
                         f"--restart {self.out or 'FILE'} continues from the last checkpoint\n")
        sys.stderr.flush()
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)

    def local_code(self):
        if self.writer is not None and getattr(self.writer, "failure", None) is not None:
            return OUTPUT_FAILED
        return int(self.received)

    def poll(self):
        """True if the run is to stop at this step boundary (on every rank alike)."""
        code = self.local_code()
        if self.comm is not None:
            from mpi4py import MPI       # only under MPI (the comm came from it)
            code = self.comm.allreduce(code, op=MPI.MAX)
        if code:
            self.code = code
        return bool(code)

    @property
    def signum(self):
        """The signal that stopped the run (0: none, or an output failure)."""
        return self.code if 0 < self.code < OUTPUT_FAILED else 0

    @property
    def output_failed(self):
        return self.code == OUTPUT_FAILED

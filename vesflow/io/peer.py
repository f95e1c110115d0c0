"""The writer of MPI ranks other than 0: no file, the same checkpoint decisions.

Rank 0 writes the one HDF5 file (every rank holds the whole state, vesflow.parallel); the
other ranks take this stand-in so that a run's control flow is the same on every rank: it
decides which checkpoints are due exactly as OutputWriter does and calls `on_checkpoint`
for them.
"""
from __future__ import annotations

from .writer import OutputWriter


class PeerWriter:
    """Run skips forming a frame's fields for it."""

    is_peer = True

    def __init__(self, checkpoint_every=None, last_checkpoint_time=None):
        self.checkpoint_every = None if checkpoint_every is None else float(checkpoint_every)
        self.last_checkpoint_time = None if last_checkpoint_time is None else float(last_checkpoint_time)
        self.on_checkpoint = []

    checkpoint_due = OutputWriter.checkpoint_due

    def write_checkpoint(self, state, force=False):
        """OutputWriter.write_checkpoint without the file."""
        if "time" not in state:
            raise ValueError("write_checkpoint: the state needs a 'time' entry")
        if not force and not self.checkpoint_due(state["time"]):
            return False
        self.last_checkpoint_time = float(state["time"])
        for fn in list(self.on_checkpoint):
            fn(state)
        return True

    def write_frame(self, **fields):
        pass

    def write_steps(self, rows):
        pass

    def write_timings(self, timings):
        pass

    def write_attrs(self, **attrs):
        pass

    def flush(self):
        pass

    def close(self):
        pass

"""HDF5 output of a run: writer, reader, checkpoint and restart.

One file per run, in the layout of ``docs/reference/output.md`` (the user-facing
contract, ``docs/reference/cli.md``).  The writer flushes after every frame, step batch,
timing update and checkpoint, through a journaled file layer (journal.py): a run
killed at any moment (even by SIGKILL) or a write that fails (a full disk, an I/O
error) leaves the file as it was after its last flush; the file is locked while
it is written.

Not rank-aware: rank 0 writes (every rank holds the whole state, vesflow.parallel); the
other ranks take a PeerWriter, which keeps the checkpoint decisions without a file.

Public names:
    OutputWriter            create (or reopen for restart) and append to a run file
    PeerWriter              the stand-in of MPI ranks other than 0
    read_output, RunOutput  read frames, steps, attributes, timings
    iter_frames             one frame at a time (for long runs and the renderer)
    read_checkpoint         the latest restartable state as a dict
    read_attributes         the root attributes only (scene, options, p, ...)
    STEP_REASONS            codes of the /steps/reason column
"""
from .layout import (FORMAT_VERSION, STEP_COLUMNS, STEP_REASONS, TIMING_KEYS, grid_size,
                     n_coefficients)
from .reader import RunOutput, frame_fields, iter_frames, read_attributes, read_checkpoint, read_output
from .peer import PeerWriter
from .writer import OutputWriter

__all__ = ["OutputWriter", "PeerWriter", "RunOutput", "read_output", "iter_frames", "read_checkpoint", "read_attributes", "frame_fields",
           "STEP_REASONS", "STEP_COLUMNS", "TIMING_KEYS", "grid_size", "n_coefficients", "FORMAT_VERSION"]

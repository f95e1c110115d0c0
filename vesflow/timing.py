"""Stage timers: PETSc log events (so -log_view shows the split of the paper's Table 3) plus wall-clock totals.

The columns of the table (STAGES) are exclusive and add up to the stepping time.  The finer
stages of DETAIL say where a column's time goes; each is a PETSc event of its own
(`VesSelfSetup`, `VesPcBlocks`, ...) and a wall-clock total in `Timers.detail`.  A detail stage
is counted in its column (ALIASES) unless it runs inside an open column stage (the
preconditioner blocks and factors are timed inside `setup`): then only in `detail`.
"""
from __future__ import annotations

import time

STAGES = ("setup", "self", "near", "far", "repar", "other")
# fine set-up stages -> the column they belong to
ALIASES = {"self_setup": "setup", "near_setup": "setup", "near_map": "setup", "far_setup": "setup", "own_setup": "setup",
           "far_own": "far", "pc_blocks": "setup",
           "pc_lu": "setup", "forces": "other", "rhs": "other", "correction": "other",
           "collision": "other", "output": "other", "quad_adapt": "other", "reparam": "repar",
           "gather": "other",     # gather: MPI exchanges of the vesicle partition (vesflow.parallel)
           "wall_setup": "setup", "wall": "far"}   # a container's wall (vesflow.layerpot.wall)
DETAIL = tuple(ALIASES)


class Timers:
    """Stage times (STAGES columns, DETAIL stages) and counts; ``with timers.stage(name):``."""

    def __init__(self, use_petsc=True):
        self.total = {s: 0.0 for s in STAGES}
        self.detail = {s: 0.0 for s in DETAIL}
        self.counts = {}
        self._t0 = {}
        self._open = []
        self._events = {}
        if use_petsc:
            try:
                from petsc4py import PETSc
                names = {s: "Ves" + "".join(w.capitalize() for w in s.split("_")) for s in STAGES + DETAIL}
                self._events = {s: PETSc.Log.Event(n) for s, n in names.items()}
            except Exception:       # petsc4py not initialized here: wall clock only
                self._events = {}

    def start(self, name):
        self._t0[name] = time.perf_counter()
        self._open.append(name)
        if name in self._events:
            self._events[name].begin()

    def stop(self, name):
        if name in self._events:
            self._events[name].end()
        dt = time.perf_counter() - self._t0.pop(name)
        self._open.remove(name)
        self.counts[name] = self.counts.get(name, 0) + 1
        if name in ALIASES:
            self.detail[name] += dt
            column = ALIASES[name]
            if column in self._open:          # nested in its column: counted there already
                return
            name = column
        self.total[name] += dt

    def count(self, name):
        """Count an event that has no time of its own (e.g. 'solve')."""
        self.counts[name] = self.counts.get(name, 0) + 1

    def stage(self, name):
        return _Stage(self, name)

    def as_dict(self):
        d = dict(self.total)
        d["total"] = sum(self.total.values())
        return d


class NullTimers(Timers):
    """Timers that record nothing: for the layer potentials, preconditioner blocks and
    benchmarks run without a stepper's timers."""

    def __init__(self):
        super().__init__(use_petsc=False)

    def start(self, name):
        pass

    def stop(self, name):
        pass

    def count(self, name):
        pass


class _Stage:
    def __init__(self, timers, name):
        self.timers, self.name = timers, name

    def __enter__(self):
        self.timers.start(self.name)

    def __exit__(self, *exc):
        self.timers.stop(self.name)

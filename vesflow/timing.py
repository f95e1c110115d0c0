"""Stage timers: PETSc log events (so -log_view shows the split of the paper's Table 3) plus wall-clock totals."""
from __future__ import annotations

import time

STAGES = ("setup", "self", "near", "far", "repar", "other")
# finer names used inside the layer potentials map onto the table's columns
ALIASES = {"self_setup": "setup", "near_setup": "setup"}


class Timers:
    def __init__(self, use_petsc=True):
        self.total = {s: 0.0 for s in STAGES}
        self._t0 = {}
        self._events = {}
        if use_petsc:
            try:
                from petsc4py import PETSc
                self._events = {s: PETSc.Log.Event(f"Ves{s.capitalize()}") for s in STAGES}
            except Exception:       # petsc4py not initialized here: wall clock only
                self._events = {}

    def start(self, name):
        name = ALIASES.get(name, name)
        self._t0[name] = time.perf_counter()
        if name in self._events:
            self._events[name].begin()

    def stop(self, name):
        name = ALIASES.get(name, name)
        if name in self._events:
            self._events[name].end()
        self.total[name] += time.perf_counter() - self._t0.pop(name)

    def stage(self, name):
        return _Stage(self, name)

    def as_dict(self):
        d = dict(self.total)
        d["total"] = sum(self.total.values())
        return d


class _Stage:
    def __init__(self, timers, name):
        self.timers, self.name = timers, name

    def __enter__(self):
        self.timers.start(self.name)

    def __exit__(self, *exc):
        self.timers.stop(self.name)

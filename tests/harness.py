"""Shared by the stability and robustness suites: a Recorder that adds invariants to every
frame, a simulate() that runs a scene text through vesflow.simulation.Run, the sheared pair."""
from __future__ import annotations

import numpy as np

from vesflow import collision, options as O, scene as S, study
from vesflow.errors import NumericalFailure
from vesflow.reparam import spectral_energy
from vesflow.simulation import Run
from vesflow.surface import Surface


class Recorder(study.Recorder):
    """study.Recorder plus, at every frame, the mesh-quality energy E (vesflow.reparam.
    spectral_energy) and the number of grid points on or behind another surface; subclasses
    add more through frame_extras."""

    def write_frame(self, *, coefficients, **kw):
        super().write_frame(coefficients=coefficients, **kw)
        p = int(round(np.sqrt(coefficients.shape[-1] + 1))) - 1
        self.frames[-1]["mesh_energy"] = spectral_energy(coefficients, p).tolist()
        surf = Surface(coefficients, p)
        self.frames[-1]["contacts"] = collision.contacts(surf, self.q_gap) if surf.n_vesicles > 1 else 0
        self.frames[-1].update(self.frame_extras(coefficients, p))

    def frame_extras(self, coefficients, p):
        return {}


def simulate(text, recorder=Recorder, allow_failure=False, **options):
    """Run a scene text with options; returns (run, recorder), plus the NumericalFailure
    message (or None) when allow_failure."""
    sc = S.parse_scene(text)
    opts = O.read_options(O.dict_getter(options), sc)
    rec = recorder(opts["q_near"])
    run = Run(sc, opts, writer=rec)
    failure = None
    try:
        run.run()
    except NumericalFailure as e:
        if not allow_failure:
            raise
        failure = str(e)
    return (run, rec, failure) if allow_failure else (run, rec)


def rejections(rec):
    """Rejected steps counted by reason."""
    out = {}
    for r in rec.steps:
        if not r[2]:
            out[r[5]] = out.get(r[5], 0) + 1
    return out


def pair_scene(dx, dz, p, T, *, shape="oblate", reduced_volume=0.9, dt=0.05, every=0.05, kb=0.05, extra=""):
    """Two vesicles at (-dx, 0, dz) and (dx, 0, -dz) in shear u = (z, 0, 0): they meet when
    the vertical offset 2 dz is below their thickness."""
    ves = f'shape = "{shape}"\nreduced_volume = {reduced_volume}\nbending_modulus = {kb}'
    return f"""
title = "pair"
{extra}
[flow]
type = "shear"
rate = 1.0
[discretization]
p = {p}
[time]
horizon = {T}
dt = {dt}
[output]
every = {every}
[[vesicle]]
{ves}
center = [{-dx}, 0.0, {dz}]
[[vesicle]]
{ves}
center = [{dx}, 0.0, {-dz}]
"""

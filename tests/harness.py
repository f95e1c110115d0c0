"""The one helper module of the tests (tests import from here, never from each other):
paths and environments (ROOT, shared_env, clean_env); a Recorder that adds invariants to every
frame, a simulate() that runs a scene text through vesflow.simulation.Run, the sheared pair."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from vesflow import collision, options as O, scene as S, study
from vesflow.errors import NumericalFailure
from vesflow.reparam import spectral_energy
from vesflow.simulation import Run
from vesflow.surface import Surface


ROOT = Path(__file__).resolve().parents[1]     # the tree (runs/, tools/, benchmarks/)


def shared_env():
    """The shared PETSc environment: the one the running venv is layered on (its .shared-env,
    tools/layered_venv.sh), or the running environment itself."""
    mark = Path(sys.prefix) / ".shared-env"
    return Path(mark.read_text().strip()) if mark.is_file() else Path(sys.prefix)


def clean_env(**extra):
    """The environment of a subprocess that must find vesflow by itself (no PYTHONPATH), one
    thread, off-screen rendering."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", VTK_DEFAULT_OPENGL_WINDOW="vtkEGLRenderWindow")
    env.update(extra)
    return env


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


def stimson_jeffery(distance, radius=1.0, n_terms=None):
    """The drag correction lambda = F / (6 pi mu a U) of two equal rigid spheres (radius a)
    translating with equal velocity U along their line of centres, centre distance `distance`
    (Stimson & Jeffery 1926, Proc. R. Soc. A 111, 110; the exact series in bispherical
    coordinates, cosh alpha = distance / (2 a)):

        lambda = 4/3 sinh(alpha) sum_{n>=1} n (n+1) / ((2n-1)(2n+3))
                 [1 - (4 sinh^2((n+1/2) alpha) - (2n+1)^2 sinh^2(alpha))
                      / (2 sinh((2n+1) alpha) + (2n+1) sinh(2 alpha))].

    Each sphere under the same force F then falls at U = U_Stokes / lambda.  The bracket is
    evaluated with e^{-(2n+1) alpha} factored out (no overflow); terms decay like
    n^2 e^{-(2n+1) alpha}, summed until below 1e-17 of the sum (or n_terms)."""
    alpha = np.arccosh(distance / (2.0 * radius))
    n = np.arange(1, (n_terms or int(60.0 / alpha) + 10) + 1, dtype=float)
    k = 2.0 * n + 1.0
    e = np.exp(-k * alpha)
    one_minus = (((2.0 + k * np.sinh(2 * alpha) + k ** 2 * np.sinh(alpha) ** 2) * e - 2.0 * e * e)
                 / (1.0 - e * e + k * np.sinh(2 * alpha) * e))
    terms = n * (n + 1) / ((2 * n - 1) * (2 * n + 3)) * one_minus
    return 4.0 / 3.0 * np.sinh(alpha) * terms.sum()

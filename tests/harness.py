"""The one helper module of the tests (tests import from here, never from each other):
paths and environments (ROOT, shared_env, clean_env); synthetic run files written with the
io writer, no simulation (synthetic_frames, write_synthetic, write_pair_run); a Recorder that
adds invariants to every frame, a simulate() that runs a scene text through
vesflow.simulation.Run, the sheared pair; the cases and invariants of the stability suites."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

from vesflow import collision, options as O, scene as S, sph, study
from vesflow.errors import NumericalFailure
from vesflow.io import OutputWriter
from vesflow.reparam import spectral_energy
from vesflow.shapes import make_shape
from vesflow.simulation import Run
from vesflow.surface import Surface


ROOT = Path(__file__).resolve().parents[1]     # the tree (runs/, tools/, benchmarks/)


def shared_env():
    """The shared PETSc environment: the one the running venv is layered on (its .shared-env,
    tools/layered_venv.sh), or the running environment itself."""
    mark = Path(sys.prefix) / ".shared-env"
    return Path(mark.read_text().strip()) if mark.is_file() else Path(sys.prefix).resolve()


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


# -------------------------------------------------------------- synthetic run files
def unit_sphere_grid(p):
    """(M, 3) unit-sphere points of the p-grid (cos(theta) descending, latitude-major)."""
    x, _ = np.polynomial.legendre.leggauss(p + 1)
    theta = np.arccos(x[::-1])
    phi = np.pi * np.arange(2 * p) / p
    T, P = np.meshgrid(theta, phi, indexing="ij")
    return np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1).reshape(-1, 3)


def synthetic_frames(p=8, n_vesicles=3, n_frames=4, dt=0.5, seed=0):
    """Spheres of radius 1 moving along x (vesicle v at speed 0.5 (v + 1)), a
    tension that varies over the surface and in time, a rigid-rotation velocity."""
    rng = np.random.default_rng(seed)
    u = unit_sphere_grid(p)
    M, C = len(u), (p + 1) ** 2 - 1
    N = n_vesicles
    frames = []
    for k in range(n_frames):
        t = k * dt
        speed = 0.5 * (np.arange(N) + 1)
        c = np.zeros((N, 3))
        c[:, 0] = 3.0 * (np.arange(N) - (N - 1) / 2) + speed * t
        c[:, 2] = 0.3 * np.arange(N)
        pts = c[:, None, :] + u[None]
        vel = np.zeros((N, M, 3))
        vel[..., 0] = speed[:, None]
        vel += 0.3 * np.cross([0.0, 1.0, 0.0], u)[None]  # rotation about y
        frames.append(dict(
            time=t, points=pts, coefficients=rng.standard_normal((N, 3, C)),
            tension=u[None, :, 2] * (1 + np.arange(N))[:, None] + np.sin(t) * u[None, :, 0],
            area=np.full(N, 4 * np.pi) * (1 + 1e-6 * k), volume=np.full(N, 4 * np.pi / 3) * (1 - 1e-6 * k),
            centroid=c, bending_energy=np.full(N, 0.1 * 4 * np.pi) + 0.01 * k, velocity=vel))
    return frames


def write_synthetic(path, p=8, n_vesicles=3, n_frames=4, dt=0.5, checkpoint_every=1, velocity=True):
    frames = synthetic_frames(p, n_vesicles, n_frames, dt)
    with OutputWriter(path, scene_text='title = "synthetic"\n', options_text="-ves_p 8",
                      version="test", p=p, n_vesicles=n_vesicles, periodic_length=0.0) as w:
        for k, fr in enumerate(frames):
            kw = dict(fr)
            if not velocity:
                kw.pop("velocity")
            w.write_frame(**kw)
            w.write_steps([dict(time=fr["time"], dt=dt, accepted=0, ksp_its=3, error_estimate=2.0,
                                reason="error_estimate"),
                           (fr["time"], dt / 2, 1, 5, 0.1, "accepted"),
                           (fr["time"] + dt / 2, dt / 2, 1, 4, 0.2, 0)])
            if checkpoint_every and k % checkpoint_every == 0:
                w.write_checkpoint(dict(time=fr["time"], coefficients=fr["coefficients"], dt=dt / 2,
                                        step=k, stepper=dict(name="sbdf1", history=None)))
        w.write_timings(dict(setup=0.5, self=1.0, near=0.25, far=0.125, repar=0.0625, other=0.0, total=1.9375))
    return frames


def pair_centres(n_frames, separation):
    """Centres (F, 2, 3): the upper vesicle starts at (-1.6, 0, 0.4), the lower one
    opposite; they pass (closest centre distance 2.6) and end `separation` apart."""
    z_end = 0.4 + 0.4
    x_end = np.sqrt(max((separation / 2) ** 2 - z_end ** 2, 0.0))
    x = np.linspace(-1.6, x_end, n_frames)
    z = 0.4 + 0.7 * np.exp(-(x / 1.5) ** 2) + 0.4 * (1 + np.tanh(x)) / 2
    c = np.stack([x, np.zeros_like(x), z], axis=1)
    return np.stack([c, -c], axis=1)


def write_pair_run(path, p=8, n_frames=30, horizon=12.0, separation=10.0, title="two vesicles in shear",
                   period=0.0, centres=None, shape="oblate", velocity=True):
    """Write the run file; returns the centres (F, N, 3).  centres overrides the pair's
    trajectory (any number of vesicles); velocity=False leaves /frames/velocity out."""
    centres = pair_centres(n_frames, separation) if centres is None else np.asarray(centres, dtype=float)
    F, N = centres.shape[:2]
    unit = make_shape(shape, p, reduced_volume=0.85 if shape == "oblate" else None, rotation=(0.0, 25.0, 0.0))
    T = sph.transform(p)
    with OutputWriter(path, scene_text=f'title = "{title}"\n' if title else "", options_text="", version="test",
                      p=p, n_vesicles=N, periodic_length=period) as w:
        for k, t in enumerate(np.linspace(0.0, horizon, F)):
            coeffs = np.repeat(unit[None], N, axis=0)
            coeffs[:, :, 0] += np.sqrt(4 * np.pi) * centres[k]
            pts = np.moveaxis(T.synth(coeffs), -2, -1)                        # (N, M, 3)
            rel = pts - centres[k][:, None, :]
            tension = rel[..., 0] * rel[..., 2] + 0.1 * np.sin(t)
            vel = np.zeros_like(pts)
            vel[..., 0] = pts[..., 2]
            w.write_frame(time=t, points=pts, coefficients=coeffs, tension=tension, area=np.full(N, 4 * np.pi),
                          volume=np.full(N, 4 * np.pi / 3 * 0.85), centroid=centres[k],
                          bending_energy=np.zeros(N), velocity=vel if velocity else None)
    return centres


# -------------------------------------------------------------- the robustness and stability suites
def robustness_pair(dx, dz, p, T, extra="", dt=0.05):
    return pair_scene(dx, dz, p, T, every=0.1, extra=extra, dt=dt)


def run_pair(text, **options):
    return simulate(text, allow_failure=True, **options)


def _long_axis_angle(coeffs, p):
    """Angle in the shear (x, z) plane of the longest principal axis, in (-pi/2, pi/2]."""
    X = Surface(coeffs, p).points()[0]
    X = X - X.mean(axis=0)
    w, v = np.linalg.eigh(X.T @ X)
    a = v[:, -1]
    return float(np.arctan2(a[2], a[0]) if a[0] >= 0 else np.arctan2(-a[2], -a[0]))


class AngleRecorder(Recorder):
    """Recorder plus the long-axis angle in the shear plane."""

    def frame_extras(self, coefficients, p):
        return {"angle": _long_axis_angle(coefficients, p)}


def simulate_angles(text, **options):
    """simulate() with the AngleRecorder (the stability suites)."""
    return simulate(text, recorder=AngleRecorder, **options)


def invariants(name, run, rec, *, area_tol=1e-6, mesh_factor=5.0, box=50.0):
    """Check and print the invariants of a finished run; returns them as a dict."""
    steps = rec.steps
    acc = [r for r in steps if r[2]]
    rej = {}
    for r in steps:
        if not r[2]:
            rej[r[5]] = rej.get(r[5], 0) + 1
    area = np.array([f["area"] for f in rec.frames]) / np.asarray(run.area0)
    vol = np.array([f["volume"] for f in rec.frames]) / np.asarray(run.volume0)
    E = np.array([f["mesh_energy"] for f in rec.frames])
    gaps = [f["min_gap"] for f in rec.frames]
    cent = run.stepper.surface.centroid()
    inv = {"accepted": len(acc), "rejected": rej, "t": run.t, "frames": len(rec.frames),
           "area_drift": float(np.abs(area - 1).max()), "volume_drift": float(np.abs(vol - 1).max()),
           "mesh_energy_ratio": float((E / E[0]).max()), "min_gap": float(min(gaps)),
           "contacts": int(max(f["contacts"] for f in rec.frames)),
           "max_its": int(max(r[3] for r in acc)) if acc else 0}
    print(f"\n[stability] {name}: " + ", ".join(f"{k} = {v:.3g}" if isinstance(v, float) else f"{k} = {v}"
                                              for k, v in inv.items()))
    assert run.t == pytest.approx(run.horizon, rel=1e-12) or run.counts["accepted"] == run.opts["ts_max_steps"]
    assert all(r[5] == "accepted" for r in acc)                  # GMRES converged on every accepted step
    assert run.stepper.surface.n_vesicles == len(run.area0)       # no vesicle lost ...
    assert np.all(np.isfinite(run.stepper.coeffs)) and np.abs(cent).max() < box   # ... or thrown away
    assert inv["contacts"] == 0 and inv["min_gap"] > 0           # no intersection at any frame
    assert inv["area_drift"] < area_tol and inv["volume_drift"] < area_tol
    assert inv["mesh_energy_ratio"] < mesh_factor
    return inv


SHEAR = "[flow]\ntype = \"shear\"\nrate = 1.0"

CROWD = """
title = "crowd"
[flow]
type = "shear"
rate = 1.0
[discretization]
p = {p}
[time]
horizon = {T}
dt = 0.02
[output]
every = {every}
[repulsion]
radius = {R}
[[lattice]]
volume_fraction = 0.35
count = 27
seed = 3
gap = 0.05
vesicle = {{ shape = "oblate", reduced_volume = 0.9, bending_modulus = 0.1 }}
"""

BICONCAVE = """
title = "biconcave"
{flow}
[discretization]
p = {p}
[time]
horizon = {T}
dt = 0.02
[output]
every = {every}
[[vesicle]]
shape = "biconcave"
reduced_volume = 0.65
center = [0.0, 0.0, 0.0]
rotation = [0.0, 0.7, 0.0]
bending_modulus = 0.05
"""

LAMBDA10 = """
title = "tumbling"
[flow]
type = "shear"
rate = 1.0
[discretization]
p = {p}
[time]
horizon = {T}
dt = 0.05
[output]
every = {every}
[[vesicle]]
shape = "prolate"
reduced_volume = 0.8
rotation = [0.0, 1.2, 0.0]
viscosity_contrast = 10.0
bending_modulus = 0.1
"""

ONE = """
title = "one"
[flow]
type = "shear"
rate = 1.0
[discretization]
p = 6
[time]
horizon = 0.5
dt = 0.05
[output]
every = 0.1
[[vesicle]]
shape = "oblate"
reduced_volume = 0.9
"""


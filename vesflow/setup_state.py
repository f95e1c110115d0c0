"""The initial state of a run from its scene: shapes, vesicle parameters, physics, the periodic cell.

Below the surfaces, forces, layer potentials and stepping: what the scene says, turned into the
numbers a stepper starts from (position coefficients (N, 3, C), VesicleParams, Physics).
"""
from __future__ import annotations

import numpy as np

from . import sph
from .shapes import euler_zyz, make_shape, unit_shape_coeffs
from .surface import Surface

# the shapes whose reduced volume is a shape parameter (sphere and ellipsoid are given by their axes)
REDUCED_VOLUME_SHAPES = ("oblate", "prolate", "biconcave")


class VesicleParams:
    """Per-vesicle physics: bending modulus, viscosity contrast, excess density (arrays of N)."""

    def __init__(self, kappa, lam, drho, viscosity=1.0):
        self.kappa = np.asarray(kappa, dtype=float)
        self.lam = np.asarray(lam, dtype=float)
        self.drho = np.asarray(drho, dtype=float)
        self.mu = float(viscosity)

    @property
    def alpha(self):
        return 0.5 * (1.0 + self.lam)

    def take(self, idx):
        """The parameters of the vesicles idx (this rank's, vesflow.parallel)."""
        return VesicleParams(self.kappa[idx], self.lam[idx], self.drho[idx], self.mu)


class Physics:
    """Scene physics for the stepper: background flow, gravity, repulsion radius (0 = off)."""

    def __init__(self, flow=None, flow_args=None, gravity=None, repulsion_radius=0.0, viscosity=1.0):
        self.flow, self.flow_args = flow, dict(flow_args or {})
        self.gravity = None if gravity is None else np.asarray(gravity, dtype=float)
        self.repulsion_radius = float(repulsion_radius)
        self.viscosity = float(viscosity)


def initial_coefficients(scene):
    """Position coefficients (N, 3, C) of the scene's vesicles."""
    p = scene.p
    out = np.empty((scene.n_vesicles, 3, sph.n_coeffs(p)))
    for k, v in enumerate(scene.vesicles):
        out[k] = make_shape(v.shape, p, radius=v.radius, center=v.center, rotation=v.rotation,
                            reduced_volume=v.reduced_volume if v.shape in REDUCED_VOLUME_SHAPES else None,
                            axes=v.axes)
    return out


def wall_coefficients(wall):
    """Position coefficients (3, C_w) of a [wall] container (vesflow.scene.model.Wall) at its
    degree: the ellipsoid of its semi-axes, rotated about its centre and moved there."""
    c = euler_zyz(wall.rotation) @ unit_shape_coeffs("ellipsoid", wall.p, axes=wall.axes)
    c[:, 0] += np.sqrt(4.0 * np.pi) * np.asarray(wall.center, dtype=float)
    return c


def vesicle_params(scene):
    """Bending moduli, viscosity contrasts and density differences of the scene's vesicles."""
    ves = scene.vesicles
    return VesicleParams([v.bending_modulus for v in ves], [v.viscosity_contrast for v in ves],
                         [v.excess_density for v in ves], scene.fluid.viscosity)


def physics(scene):
    """The scene's background flow, gravity, repulsion radius and viscosity as a Physics."""
    flow, args = None, {}
    if scene.flow is not None and (scene.flow.rate or scene.flow.amplitude):   # rate 0: no flow, no cost
        flow = scene.flow.type
        if flow == "taylor_green":
            args = {"amplitude": scene.flow.amplitude, "period": scene.periodic_length}
        elif flow == "poiseuille":
            args = {"rate": scene.flow.rate, "radius": scene.flow.radius}
        else:
            args = {"rate": scene.flow.rate}
    g = scene.gravity.g if scene.gravity is not None else None
    R = scene.repulsion.radius if scene.repulsion is not None else 0.0
    return Physics(flow, args, g, R or 0.0, scene.fluid.viscosity)


def scene_period(scene):
    """The period of a triply periodic scene, None in free space."""
    return scene.periodic_length or None


def wrap_into_cell(coeffs, p, period, centroid=None):
    """Move each vesicle by the lattice vector -L k, k = floor(centroid / L), so that its
    centroid lies in [0, L)^3: the l = 0 coefficient of x, y, z changes by -sqrt(4 pi) L k.
    Returns (coefficients, k (N, 3) integers); the input is not changed."""
    if centroid is None:
        centroid = Surface(coeffs, p).centroid()
    k = np.floor(np.asarray(centroid) / period).astype(np.int64)
    if not np.any(k):
        return coeffs, k
    out = np.array(coeffs, dtype=float)
    out[:, :, 0] -= np.sqrt(4.0 * np.pi) * period * k
    return out, k

"""The initial state of a scene: its vesicles' position coefficients (method reference, section 1).

Below the layer potentials and the stepping: the cost model (vesflow.costs) and a run
(vesflow.simulation) build the same initial surfaces from it.
"""
from __future__ import annotations

import numpy as np

from . import sph
from .shapes import make_shape

# the shapes whose reduced volume is a shape parameter (sphere and ellipsoid are given by their axes)
REDUCED_VOLUME_SHAPES = ("oblate", "prolate", "biconcave")


def initial_coefficients(scene):
    """Position coefficients (N, 3, C) of the scene's vesicles."""
    p = scene.p
    out = np.empty((scene.n_vesicles, 3, sph.n_coeffs(p)))
    for k, v in enumerate(scene.vesicles):
        out[k] = make_shape(v.shape, p, radius=v.radius, center=v.center, rotation=v.rotation,
                            reduced_volume=v.reduced_volume if v.shape in REDUCED_VOLUME_SHAPES else None,
                            axes=v.axes)
    return out

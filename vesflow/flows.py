"""Background flows u_inf (docs/reference/scene.md, scene key [flow])."""
from __future__ import annotations

import numpy as np

FLOWS = ("shear", "extensional", "poiseuille", "taylor_green")


def background_velocity(kind, X, rate=0.0, radius=1.0, amplitude=0.1, period=None):
    """u_inf at points X (..., 3).

    shear        rate * (z, 0, 0)
    extensional  rate * (-x, y/2, z/2)
    poiseuille   rate * (1 - (y^2 + z^2) / radius^2) e_x
    taylor_green paper (4.1) with k = 2 pi / L: alpha (sin kx cos ky sin kz, -cos kx sin ky sin kz, 0);
                 the paper prints "+" in the y component, which is not divergence-free
                 (div = 2 alpha k cos kx cos ky sin kz); the sign is corrected here
    """
    X = np.asarray(X, dtype=float)
    x, y, z = X[..., 0], X[..., 1], X[..., 2]
    u = np.zeros_like(X)
    if kind is None:
        return u
    if kind == "shear":
        u[..., 0] = rate * z
    elif kind == "extensional":
        u[..., 0], u[..., 1], u[..., 2] = -rate * x, 0.5 * rate * y, 0.5 * rate * z
    elif kind == "poiseuille":
        u[..., 0] = rate * (1.0 - (y * y + z * z) / radius ** 2)
    elif kind == "taylor_green":
        if not period:
            raise ValueError("taylor_green flow needs the period L of the domain")
        k = 2.0 * np.pi / period
        u[..., 0] = amplitude * np.sin(k * x) * np.cos(k * y) * np.sin(k * z)
        u[..., 1] = -amplitude * np.cos(k * x) * np.sin(k * y) * np.sin(k * z)
    else:
        raise ValueError(f"flow type {kind!r}: must be one of {', '.join(FLOWS)}")
    return u

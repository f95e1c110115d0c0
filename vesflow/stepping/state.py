"""The state of a run between steps: what a step starts from and what a checkpoint stores."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..stepper import Solution


@dataclass
class State:
    """Position coefficients X (N, 3, C) at time t; the velocity u (N, 3, C) and tension sigma
    (N, C) of the last solve, the initial guess of the next one when `guess`; image (N, 3): the
    lattice vectors / L the periodic wrap took off each vesicle (0 in free space); wall: a
    container's density (3 C_w,) of the last solve (its part of the guess), None without."""

    coeffs: np.ndarray
    u: np.ndarray
    sigma: np.ndarray
    image: np.ndarray
    t: float
    guess: bool = False
    wall: np.ndarray | None = None

    def copy(self):
        return State(self.coeffs.copy(), self.u.copy(), self.sigma.copy(), self.image.copy(), self.t, self.guess,
                     None if self.wall is None else self.wall.copy())

    def load(self, stepper):
        """Put the stepper at this state (its coefficients, time and initial guess)."""
        stepper.coeffs = self.coeffs.copy()
        stepper.time = self.t
        stepper.last = Solution(self.u, self.sigma, 0, 0, self.wall) if self.guess else None

    def advanced(self, stepper, sol):
        """The state the stepper reached with the Solution sol of its last solve."""
        return State(stepper.coeffs.copy(), sol.u, sol.sigma, self.image, stepper.time, True, sol.wall)

    @classmethod
    def initial(cls, coeffs, n_coeffs):
        N = len(coeffs)
        return cls(np.array(coeffs, dtype=float), np.zeros((N, 3, n_coeffs)), np.zeros((N, n_coeffs)),
                   np.zeros((N, 3), dtype=np.int64), 0.0, False)

    @classmethod
    def from_checkpoint(cls, ck):
        """The state of a checkpoint (vesflow.io.read_checkpoint); older files have no image."""
        coeffs = np.array(ck["coeffs"], dtype=float)
        image = (np.asarray(ck["image"], dtype=np.int64).reshape(-1, 3).copy() if "image" in ck
                 else np.zeros((len(coeffs), 3), dtype=np.int64))
        wall = np.asarray(ck["wall"], dtype=float).copy() if "wall" in ck else None
        return cls(coeffs, np.asarray(ck["u"]), np.asarray(ck["sigma"]), image, float(ck["time"]), bool(int(ck["has_last"])),
                   wall)

    def as_checkpoint(self):
        out = {"time": self.t, "coeffs": self.coeffs, "sigma": self.sigma, "u": self.u,
               "has_last": int(self.guess), "image": self.image}
        if self.wall is not None:           # a container's density: the restart's guess as the run's
            out["wall"] = self.wall
        return out

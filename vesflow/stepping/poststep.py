"""The post-step of an accepted candidate: reparameterize, restore area and volume, keep the
centroid, check collisions (paper 3.3, 3.5), and the periodic wrap."""
from __future__ import annotations

import numpy as np

from .. import collision
from ..correction import correct_area_volume
from ..reparam import reparameterize
from ..setup_state import wrap_into_cell
from ..surface import Surface


class PostStep:
    """The per-vesicle constraints of a run: area0, volume0 (N,) and the options; each rank
    processes its vesicles of the partition and the results are gathered."""

    def __init__(self, opts, p, area0, volume0, part, timers, period, q_near):
        self.opts, self.p, self.part, self.timers, self.period = opts, p, part, timers, period
        self.area0, self.volume0 = area0, volume0
        self.q_near = q_near                 # () -> the current q_near (collision detection's grid)
        self.wall = None                     # a container (vesflow.layerpot.wall.Wall): crossing it is a collision
        self.reparam_skipped = 0             # accepted steps whose reparameterization would have made contact
        self.reparam_iterated = 0            # accepted steps kept out of contact by the iterated projection

    def processed(self, coeffs, reparam, project_its=1, dt=0.0):
        """Reparameterize (if reparam), then restore area and volume (the reparameterization
        moves points tangentially but changes A and V at the discretization error, ~1e-6; the
        correction after it leaves them at -ves_correct_tol)."""
        idx = self.part.idx
        mine = self._process(coeffs[idx], reparam, project_its, _rows(self.area0, idx), _rows(self.volume0, idx), dt)
        with self.timers.stage("gather"):
            return self.part.gather(mine)

    def _process(self, coeffs, reparam, project_its, area0, volume0, dt=0.0):
        """Reparameterize, correct area and volume, then (-ves_keep_centroid) translate each
        vesicle back to the centroid the step gave it.  Neither part is motion: the
        reparameterization moves points tangentially (its shape change is the truncation error),
        the correction is a normal move psi n (3.20); on a sheared, asymmetric shape both shift
        the volume centroid, by 2e-6 ... 2e-5 per step in the accuracy-cost pair (p = 8, sdc),
        as much as the step's own error and not seen by any step-error estimate.  A rigid
        translation changes neither area, volume nor parameterization.

        The reparameterization takes up to max(-ves_reparam_max_its, -ves_reparam_rate dt)
        descent steps: the grid distorts at a rate per unit simulated time, so the descent's
        budget is per unit time too.  With a fixed budget per step (20), a run of 20 sdc steps
        reparameterized 15x less than one of 300 euler steps: every call stopped at the cap and
        the mesh energy rose to 22 instead of 16 (accuracy-cost pair, p = 8), a spatial error
        set by the number of steps, not by the tolerance."""
        o, p = self.opts, self.p
        if o["keep_centroid"]:
            c0 = Surface(coeffs, p).centroid()
        if reparam:
            with self.timers.stage("reparam"):
                coeffs, _, _, _ = reparameterize(coeffs, p, dtau_max=o["reparam_dtau_max"], tol=o["reparam_tol"],
                                                 max_its=max(o["reparam_max_its"], int(np.ceil(o["reparam_rate"] * dt))),
                                                 attenuation=o["reparam_attenuation"], project_its=project_its)
        if o["correct"] == "area_volume":
            with self.timers.stage("correction"):
                coeffs, _, _ = correct_area_volume(coeffs, p, area0, volume0,
                                                   tol=o["correct_tol"], max_its=o["correct_max_its"])
        if o["keep_centroid"]:
            coeffs = Surface(coeffs, p).translated(c0 - Surface(coeffs, p).centroid()).coeffs
        return coeffs

    def touching(self, coeffs):
        """Whether any grid point is on or behind another vesicle (this rank's points against
        every surface, the counts summed over the ranks)."""
        with self.timers.stage("collision"):
            S = Surface(coeffs, self.p)
            if self.wall is not None and not self.wall.contains(S.points().reshape(-1, 3)).all():
                return True                  # a point on or beyond the container's wall
            return self.part.sum(collision.contacts(S, self.q_near(), self.period, part=self.part)) > 0

    def wrap(self, state):
        """Periodic runs, at a step boundary: a vesicle whose centroid left the cell [0, L)^3
        is moved back by a lattice vector (exact for the periodic sums, the minimum-image near
        field and the periodic background flow), counted in state.image."""
        if self.period is None:
            return
        with self.timers.stage("other"):
            coeffs, moved = wrap_into_cell(state.coeffs, self.p, self.period)
        if np.any(moved):
            state.coeffs, state.image = coeffs, state.image + moved


def _rows(a, idx):
    """a[idx] for a per-vesicle array, a itself for a scalar."""
    a = np.asarray(a)
    return a[idx] if a.ndim else a

"""Synthetic run files for the renderer's tests and benchmark (written with the io writer,
no simulation): two oblate vesicles that pass each other in shear u = (z, 0, 0) and drift
apart, with coefficients, p-grid points, tension and velocity that agree."""
import numpy as np

from vesflow import sph
from vesflow.io import OutputWriter
from vesflow.shapes import make_shape


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

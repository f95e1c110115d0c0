"""The surfaces drawn by the renderer: frames of a run file evaluated from their
spherical-harmonic coefficients on a finer grid, or the meshes of a .pvd collection.

Run files (.h5): each frame's position coefficients (N, 3, C) of degree p are
synthesized on the q-grid (q = the resolution >= p; q + 1 Gauss-Legendre
latitudes, 2q longitudes) with sph.transform(p, q), plus the two poles
(sph.evaluate at theta = 0, pi).  Normals are analytic: n = X_t x X_p / |X_t x X_p|
(surface.py) on the grid; at a pole, where the (theta, phi) chart degenerates,
n = +-(X_t(phi = 0) x X_t(phi = pi/2)) with X_t from the m = 1 coefficients
(d lam_n^1 / d theta = sqrt((2n + 1) n (n + 1) / (16 pi)) at theta = 0, times
(-1)^(n+1) at theta = pi).  Colour fields stored on the p-grid (tension,
velocity) are expanded to degree p (sph analysis) and synthesized on the same
q-grid.  Triangles: vtk_export.surface_faces(N, q) (grid points in grid order,
then north and south pole, per vesicle).

The default resolution is the smallest q in RESOLUTIONS (and >= p) at which the
normals of adjacent triangles differ by at most MAX_FACET_ANGLE degrees on the
first, middle and last frame (up to 16 vesicles of each), i.e. no visible facets;
the facet angle falls like 1/q (p = 6 biconcave cell: 18.2 degrees at q = 24, 9.6 at 48).
Large suspensions stay within MAX_POINTS drawn points per frame (q = 48 up to 850
vesicles), with a warning if that leaves facets.

.pvd collections carry no coefficients: their meshes are drawn as stored.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from .. import sph
from ..io import frame_fields, iter_frames, read_output
from ..vtk_export import surface_faces

RESOLUTIONS = (24, 32, 40, 48, 56, 64, 80, 96, 128)  # the default resolution is the first of these (>= p) without facets
MAX_FACET_ANGLE = 8.0                 # degrees between the normals of adjacent triangles
MAX_POINTS = 4_000_000                # drawn points per frame the default resolution stays within
UNITS = {"tension": "force/length", "speed": "length/time"}


@dataclass
class FrameMesh:
    """One frame ready to draw: points (N, P, 3), normals (N, P, 3) or None, the
    triangles (T, 3) of one vesicle on its P points, colour values (N, P) or None."""

    time: float
    points: np.ndarray
    normals: np.ndarray | None
    faces: np.ndarray
    values: np.ndarray | None

    def all_faces(self):
        """Triangles (N T, 3) into the flattened (N P, 3) points."""
        N, P = self.points.shape[:2]
        return (self.faces[None] + P * np.arange(N)[:, None, None]).reshape(-1, 3)


def _pole_tangents(coeffs, p):
    """X_t at (theta = 0, phi = 0), (0, pi/2), (pi, 0), (pi, pi/2): (..., 4, 3) from
    the m = 1 coefficients (N, 3, C) (module docstring)."""
    ns, ms, ks = sph.index_tables(p)
    k = coeffs.shape[-1]
    ns, ms, ks = ns[:k], ms[:k], ks[:k]
    cos1 = np.nonzero((ms == 1) & (ks == 0))[0]
    sin1 = np.nonzero((ms == 1) & (ks == 1))[0]
    n = ns[cos1].astype(float)                              # the same degrees for both
    d0 = sph.SQRT2 * np.sqrt((2 * n + 1) * n * (n + 1) / (16 * np.pi))
    dpi = d0 * (-1.0) ** (n + 1)
    a = coeffs[..., cos1]                                   # (N, 3, p)
    b = coeffs[..., sin1]
    return np.stack([a @ d0, b @ d0, a @ dpi, b @ dpi], axis=-2)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def surface_on_grid(coeffs, p, q):
    """Points and outward unit normals (N, (q+1) 2q + 2, 3) of surfaces with position
    coefficients (N, 3, C) of degree p: the q-grid in grid order, then north and south pole."""
    coeffs = np.asarray(coeffs, dtype=float)
    T = sph.transform(p, q)
    X = np.moveaxis(T.synth(coeffs), -2, -1)
    Xt = np.moveaxis(T.synth(coeffs, "t"), -2, -1)
    Xp = np.moveaxis(T.synth(coeffs, "p"), -2, -1)
    normals = _unit(np.cross(Xt, Xp))
    poles = np.moveaxis(sph.evaluate(coeffs, p, [0.0, np.pi], [0.0, 0.0]), -1, -2)   # (N, 2, 3)
    tg = _pole_tangents(coeffs, p)
    pole_normals = np.stack([_unit(np.cross(tg[..., 0, :], tg[..., 1, :])),
                             -_unit(np.cross(tg[..., 2, :], tg[..., 3, :]))], axis=-2)
    return np.concatenate([X, poles], axis=-2), np.concatenate([normals, pole_normals], axis=-2)


@lru_cache(maxsize=16)
def _edge_pairs(q):
    """Pairs (E, 2) of triangles of one vesicle on the q-grid that share an edge."""
    faces = surface_faces(1, q)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    tri = np.tile(np.arange(len(faces)), 3)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    edges, tri = edges[order], tri[order]
    same = np.all(edges[1:] == edges[:-1], axis=1)
    return np.stack([tri[:-1][same], tri[1:][same]], axis=1)


def facet_angle(coeffs, p, q):
    """Largest angle (degrees) between the normals of adjacent triangles of the surfaces
    (N, 3, C) drawn on the q-grid."""
    pts, _ = surface_on_grid(coeffs, p, q)
    f = surface_faces(1, q)
    a, b, c = pts[:, f[:, 0]], pts[:, f[:, 1]], pts[:, f[:, 2]]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    pairs = _edge_pairs(q)
    cos = np.einsum("nek,nek->ne", n[:, pairs[:, 0]], n[:, pairs[:, 1]])
    return float(np.degrees(np.arccos(np.clip(cos.min(), -1.0, 1.0))))


def grid_points(q):
    """Points per vesicle drawn on the q-grid (grid and poles)."""
    return (q + 1) * 2 * q + 2


def auto_resolution(coeffs, p, n_vesicles=1):
    """The default resolution for surfaces (N, 3, C) (module docstring), within a budget
    of MAX_POINTS drawn points for n_vesicles (a warning says when that leaves facets)."""
    fits = [q for q in RESOLUTIONS if q >= p and n_vesicles * grid_points(q) <= MAX_POINTS] or [p]
    for q in fits:
        if facet_angle(coeffs, p, q) <= MAX_FACET_ANGLE:
            return q
    q = fits[-1]
    import warnings
    why = (f"finer grids exceed {MAX_POINTS:.0e} drawn points" if q < max(RESOLUTIONS[-1], p)
           else "the finest default grid")
    warnings.warn(f"render: {n_vesicles} vesicles at resolution {q}: adjacent triangles differ by up to "
                  f"{facet_angle(coeffs, p, q):.0f} degrees ({why}); --resolution Q sets the grid", stacklevel=2)
    return q


def scalar_on_grid(values, p, q):
    """Grid values (N, M) on the p-grid -> (N, (q+1) 2q + 2) on the q-grid and poles
    (the degree-p expansion, evaluated)."""
    values = np.asarray(values, dtype=float)
    c = sph.transform(p).analysis(values)
    fine = sph.transform(p, q).synth(c)
    poles = sph.evaluate(c, p, [0.0, np.pi], [0.0, 0.0])
    return np.concatenate([fine, poles], axis=-1)


def _title_of(scene_text):
    import tomllib
    try:
        t = tomllib.loads(scene_text or "").get("title")
    except tomllib.TOMLDecodeError:
        return None
    return str(t) if t else None


class RunFrames:
    """Frames of a run file (.h5), drawn from their coefficients at resolution q."""

    kind = "h5"

    def __init__(self, path, frames=None, resolution=None):
        self.path = Path(path)
        out = read_output(self.path, frames=frames, fields=[])
        self.p = out.p
        self.index = np.asarray(out.frame_index)
        if resolution is None and len(self.index):
            pick = sorted({0, len(self.index) // 2, len(self.index) - 1})
            ves = np.unique(np.linspace(0, out.n_vesicles - 1, min(16, out.n_vesicles)).round().astype(int))
            sample = np.concatenate([fr["coefficients"][ves] for fr in
                                     iter_frames(self.path, fields=["coefficients"], frames=self.index[pick])])
            resolution = auto_resolution(sample, self.p, out.n_vesicles)
        q = self.p if resolution is None else int(resolution)
        if q < self.p:
            raise ValueError(f"render: resolution = {q}: must be an integer >= p = {self.p} "
                             f"(the run's degree; default: the smallest of {RESOLUTIONS} without facets)")
        self.q = q
        self.times = [float(t) for t in out.time]
        self.title = _title_of(out.attrs.get("scene", ""))
        self.period = float(out.attrs.get("periodic_length", 0.0) or 0.0)
        self.fields = set(frame_fields(self.path))
        self.faces = surface_faces(1, self.q)
        self.wall = run_wall(self.path)

    def read(self, positions, color):
        """FrameMesh of the selected frames at the given positions (into self.times)."""
        names = ["coefficients"] + {"tension": ["tension"], "speed": ["velocity"]}.get(color, [])
        for fr in iter_frames(self.path, fields=names, frames=self.index[list(positions)]):
            pts, nrm = surface_on_grid(fr["coefficients"], self.p, self.q)
            vals = None
            if color == "tension":
                vals = scalar_on_grid(fr["tension"], self.p, self.q)
            elif color == "speed":
                vel = scalar_on_grid(np.moveaxis(fr["velocity"], -1, -2), self.p, self.q)   # (N, 3, P)
                vals = np.linalg.norm(vel, axis=-2)
            yield FrameMesh(fr["time"], pts, nrm, self.faces, vals)

    def scan(self, color):
        """Per frame: the drawn surface points (N, P, 3) (for framing) and the colour
        values as stored (for the colour range; None for color none)."""
        name = {"tension": "tension", "speed": "velocity"}.get(color)
        if name is not None and name not in self.fields:
            raise ValueError(f"render: color={color!r} needs point data {color!r}"
                             + (" (or velocity)" if color == "speed" else "")
                             + f"; {self.path} has no /frames/{name}. Use --color none or tension")
        T = sph.transform(self.p, self.q)
        for fr in iter_frames(self.path, fields=["coefficients"] + ([name] if name else []), frames=self.index):
            vals = None
            if name == "tension":
                vals = fr["tension"]
            elif name == "velocity":
                vals = np.linalg.norm(fr["velocity"], axis=-1)
            yield np.moveaxis(T.synth(fr["coefficients"]), -2, -1), vals


class PvdFrames:
    """Frames of a .pvd collection (meshes as stored; no coefficients, no resolution)."""

    kind = "pvd"

    def __init__(self, path, frames=None, resolution=None):
        import pyvista as pv
        self.path = Path(path)
        if resolution is not None:
            raise ValueError(f"render: resolution = {resolution}: applies to run files (.h5) only; "
                             f"{self.path.name} is a .pvd collection of stored meshes")
        self._reader = pv.get_reader(str(self.path))
        all_times = list(self._reader.time_values)
        idx = np.arange(len(all_times))
        if frames is not None:
            idx = idx[frames] if isinstance(frames, slice) else idx[np.asarray(frames)]
        self.index = idx
        self.times = [float(all_times[i]) for i in idx]
        self.title = None
        self.period = 0.0
        self.q = None

    def _mesh(self, t):
        import pyvista as pv
        self._reader.set_active_time_value(t)
        data = self._reader.read()
        if isinstance(data, pv.MultiBlock):
            blocks = [b for b in data if b is not None]
            data = blocks[0] if len(blocks) == 1 else data.combine()
        if not isinstance(data, pv.PolyData):
            data = data.extract_surface()
        return data

    def read(self, positions, color):
        for k in positions:
            t = self.times[k]
            mesh = self._mesh(t)
            pts = np.asarray(mesh.points, dtype=float)
            vid = (np.asarray(mesh.point_data["vesicle_id"]).astype(np.int64) if "vesicle_id" in mesh.point_data
                   else np.zeros(len(pts), dtype=np.int64))
            n = int(vid.max()) + 1 if len(vid) else 0
            counts = np.bincount(vid, minlength=n)
            if len(vid) and not (np.all(counts == counts[0]) and np.all(np.diff(vid) >= 0)):
                raise ValueError(f"render: {self.path}: vesicles with different point counts or "
                                 f"interleaved points cannot be drawn")
            P = counts[0] if n else 0
            faces = mesh.regular_faces.reshape(n, -1, 3) - P * np.arange(n)[:, None, None]
            if not np.all(faces == faces[:1]):
                raise ValueError(f"render: {self.path}: vesicles with different triangulations cannot be drawn")
            vals = _pvd_values(mesh, color)
            yield FrameMesh(t, pts.reshape(n, P, 3), None, faces[0],
                            None if vals is None else vals.reshape(n, P))

    def scan(self, color):
        for fm in self.read(range(len(self.times)), color):
            yield fm.points, fm.values


def _pvd_values(mesh, color):
    if color == "none":
        return None
    if color in mesh.point_data:
        return np.asarray(mesh.point_data[color], dtype=float)
    if color == "speed" and "velocity" in mesh.point_data:
        return np.linalg.norm(np.asarray(mesh.point_data["velocity"]), axis=1)
    have = sorted(k for k in mesh.point_data.keys() if k != "vesicle_id")
    raise ValueError(f"render: color={color!r} needs point data {color!r}"
                     + (" (or velocity)" if color == "speed" else "")
                     + f"; this run has {have or 'none'}. Use --color none or one of {have}")


def run_wall(path):
    """The container of a run file ([wall], /wall): (points (P, 3), normals (P, 3), faces (F, 3))
    on its grid of degree 2 p_w (smooth when drawn), or None without a wall."""
    import h5py

    with h5py.File(path, "r") as f:
        if "wall" not in f:
            return None
        coeffs, p = f["wall/coefficients"][:], int(f["wall"].attrs["p"])
    q = 2 * p
    pts, nrm = surface_on_grid(coeffs[None], p, q)
    return pts[0], nrm[0], surface_faces(1, q)


def open_frames(path, frames=None, resolution=None):
    """RunFrames or PvdFrames by suffix; clear errors for a missing file or another suffix."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"render: {path}: no such file")
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        src = RunFrames(path, frames, resolution)
    elif suffix == ".pvd":
        src = PvdFrames(path, frames, resolution)
    else:
        raise ValueError(f"render: {path}: expected a run file (.h5) or a .pvd collection")
    if not src.times:
        raise ValueError(f"render: {path} has no frames")
    return src

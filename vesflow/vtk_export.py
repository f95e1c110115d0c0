"""VTK export of a run (`vesflow export RUN.h5 --vtk DIR`): one .vtp per frame plus a .pvd
collection (opens in ParaView).

Each vesicle is a closed, outward-oriented triangulated surface: the p-grid points
(latitude-major, see docs/explanation/conventions.md) plus a north and a south pole point.
Consecutive latitudes are joined by quads split in two triangles (wrapping in
phi); each pole closes its cap with a triangle fan.  Per vesicle the points are
the M grid points in grid order, then the north pole, then the south pole, so a
vesicle is the contiguous block [v * (M + 2), (v + 1) * (M + 2)).

Poles are taken from an (N, 2, 3) array when given (/frames/poles in the run
file, e.g. Surface.pole_points()), else as the mean of the first / last ring.
Point data at the poles are ring means.  pyvista is imported lazily.
"""
from __future__ import annotations

import functools
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from .io import frame_fields, iter_frames, read_output
from .io.xdmf import ring_triangles


def grid_shape(p):
    """(nlat, nlon) of the p-grid."""
    return p + 1, 2 * p


@functools.lru_cache(maxsize=16)
def _vesicle_faces(p):
    """(2M, 3) triangles of one vesicle on M + 2 points (grid, north, south)."""
    nlat, nlon = grid_shape(p)
    M = nlat * nlon
    quads = ring_triangles(p)
    j = np.arange(nlon)
    jn = (j + 1) % nlon
    north = np.stack([np.full(nlon, M), j, jn], 1)
    last = (nlat - 1) * nlon
    south = np.stack([last + j, np.full(nlon, M + 1), last + jn], 1)
    faces = np.concatenate([north, quads, south]).astype(np.int64)
    faces.setflags(write=False)
    return faces


def surface_faces(n_vesicles, p):
    """(N * 2M, 3) triangles of N vesicles, each on its block of M + 2 points."""
    f = _vesicle_faces(p)
    off = (np.arange(n_vesicles, dtype=np.int64) * (grid_shape(p)[0] * grid_shape(p)[1] + 2))
    return (f[None, :, :] + off[:, None, None]).reshape(-1, 3)


def with_poles(values, p, poles=None):
    """Append the two pole values to grid data: (N, M, ...) -> (N, M + 2, ...).
    poles (N, 2, ...) are used when given, else the first / last ring means."""
    values = np.asarray(values, dtype=np.float64)
    nlat, nlon = grid_shape(p)
    N, M = values.shape[:2]
    if M != nlat * nlon:
        raise ValueError(f"grid data has {M} points per vesicle, expected M = 2p(p+1) = {nlat * nlon} for p={p}")
    if poles is None:
        rings = values.reshape((N, nlat, nlon) + values.shape[2:])
        poles = np.stack([rings[:, 0].mean(axis=1), rings[:, -1].mean(axis=1)], axis=1)
    else:
        poles = np.asarray(poles, dtype=np.float64)
        if poles.shape != (N, 2) + values.shape[2:]:
            raise ValueError(f"poles has shape {poles.shape}, expected {(N, 2) + values.shape[2:]}")
    return np.concatenate([values, poles], axis=1)


def frame_polydata(points, p, point_data=None, poles=None, time=None):
    """pyvista.PolyData of one frame.  points (N, M, 3) on the p-grid; point_data:
    name -> (N, M) or (N, M, k) grid values (poles get ring means); poles (N, 2, 3)
    optional.  Adds point data vesicle_id (and speed if velocity is given), cell
    data vesicle_id, field data time."""
    import pyvista as pv

    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"points has shape {points.shape}, expected (N, M, 3)")
    N = points.shape[0]
    xyz = with_poles(points, p, poles).reshape(-1, 3)
    mesh = pv.PolyData.from_regular_faces(xyz, surface_faces(N, p))
    Mp = xyz.shape[0] // max(N, 1)
    data = dict(point_data or {})
    if "velocity" in data and data["velocity"] is not None and "speed" not in data:
        data["speed"] = None  # computed from the velocity with poles
    ext = {}
    for name, v in data.items():
        if v is None or name == "speed":
            continue
        v = np.asarray(v, dtype=np.float64)
        if v.shape[:2] != points.shape[:2]:
            raise ValueError(f"point data {name!r} has shape {v.shape}, expected ({N}, {points.shape[1]}, ...)")
        ext[name] = with_poles(v, p).reshape((N * Mp,) + v.shape[2:])
    if "speed" in data:
        ext["speed"] = (np.linalg.norm(ext["velocity"], axis=1) if data["speed"] is None else
                        with_poles(np.asarray(data["speed"], dtype=np.float64), p).reshape(-1))
    for name, v in ext.items():
        mesh.point_data[name] = v
    mesh.point_data["vesicle_id"] = np.repeat(np.arange(N, dtype=np.int32), Mp)
    mesh.cell_data["vesicle_id"] = np.repeat(np.arange(N, dtype=np.int32), len(_vesicle_faces(p)))
    if time is not None:
        mesh.field_data["time"] = np.array([float(time)])
    return mesh


def write_pvd(pvd_path, entries):
    """Write a ParaView collection: entries = [(time, file relative to the pvd), ...]."""
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             "  <Collection>"]
    for t, fname in entries:
        lines.append(f'    <DataSet timestep="{float(t)!r}" group="" part="0" file={quoteattr(str(fname))}/>')
    lines += ["  </Collection>", "</VTKFile>", ""]
    Path(pvd_path).write_text("\n".join(lines))
    return Path(pvd_path)


def h5_frame_meshes(h5path, frames=None):
    """Yield (time, PolyData) for the frames of a run file (tension, velocity, speed)."""
    out = read_output(h5path, frames=slice(0, 0))
    p = out.p
    present = set(frame_fields(h5path))
    fields = ["points"] + [x for x in ("tension", "velocity", "poles") if x in present]
    for fr in iter_frames(h5path, fields=fields, frames=frames):
        pd = {k: fr[k] for k in ("tension", "velocity") if k in fr}
        # a frame written without velocity has NaN there (drawn as NaN colour)
        poles = fr.get("poles")
        if poles is not None and not np.all(np.isfinite(poles)):
            poles = None
        yield fr["time"], frame_polydata(fr["points"], p, pd, poles=poles, time=fr["time"])


def export_vtk(h5path, outdir, *, frames=None, prefix=None):
    """Export a run file to outdir/PREFIX_000000.vtp ... and outdir/PREFIX.pvd (PREFIX:
    the file's stem).  Returns the path of the .pvd."""
    h5path = Path(h5path)
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    prefix = prefix or h5path.stem
    entries = []
    for k, (t, mesh) in enumerate(h5_frame_meshes(h5path, frames=frames)):
        name = f"{prefix}_{k:06d}.vtp"
        mesh.save(outdir / name, binary=True)
        entries.append((t, name))
    wall = wall_polydata(h5path)
    if wall is not None:                    # the container, once: PREFIX_wall.vtp beside the frames
        wall.save(outdir / f"{prefix}_wall.vtp", binary=True)
    return write_pvd(outdir / f"{prefix}.pvd", entries)


def wall_polydata(h5path):
    """pyvista.PolyData of a run's container (/wall, [wall]) on its p_w-grid points and poles, or
    None without a wall."""
    import h5py

    with h5py.File(h5path, "r") as f:
        if "wall" not in f:
            return None
        pts, p = f["wall/points"][:], int(f["wall"].attrs["p"])
    return frame_polydata(pts[None], p)


__all__ = ["frame_polydata", "export_vtk", "wall_polydata", "write_pvd", "surface_faces", "with_poles", "h5_frame_meshes"]

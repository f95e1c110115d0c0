"""XDMF description of a run file (RUN.xmf beside RUN.h5): ParaView and VisIt read the frames
as a temporal collection of triangulated surfaces straight from the HDF5 datasets (no copy).

The mesh of one vesicle is its M = 2p(p+1) p-grid points in grid order (docs/explanation/conventions.md):
consecutive latitude rings joined by quads split in two triangles (wrapping in phi), each
polar cap closed by a fan over its ring (nlon - 2 triangles, no pole point), every triangle
counter-clockwise seen from outside.  Vesicle v's points are [v M, (v + 1) M) of a frame's
N M points.  The run file holds the triangles once, /mesh/triangles (T, 3), T = N (2 nlon
(nlat - 1) + 2 (nlon - 2)), and /mesh/vesicle_id (N M,).  Frame k of the XDMF file is the
hyperslab k of /frames/points (geometry) and of the per-point fields present: tension,
velocity, bending_energy_density; plus vesicle_id.
"""
from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

# frame dataset -> XDMF AttributeType of the per-point fields the description lists
POINT_FIELDS = {"tension": "Scalar", "velocity": "Vector", "bending_energy_density": "Scalar"}


def ring_triangles(p):
    """(2 nlon (nlat - 1), 3) triangles joining consecutive latitude rings of the p-grid
    (nlat = p + 1, nlon = 2p), counter-clockwise seen from outside."""
    nlat, nlon = p + 1, 2 * p
    i, j = np.meshgrid(np.arange(nlat - 1), np.arange(nlon), indexing="ij")
    i, j = i.ravel(), j.ravel()
    jn = (j + 1) % nlon
    a = i * nlon + j            # (theta_i, phi_j)
    b = i * nlon + jn           # (theta_i, phi_j+1)
    c = (i + 1) * nlon + jn     # (theta_i+1, phi_j+1)
    d = (i + 1) * nlon + j      # (theta_i+1, phi_j)
    # theta grows southwards, phi eastwards: e_theta x e_phi is the outward normal
    return np.concatenate([np.stack([a, d, c], 1), np.stack([a, c, b], 1)]).astype(np.int64)


def grid_triangles(p):
    """(T1, 3) triangles of one vesicle on its M p-grid points: the ring triangles and a fan
    over the first (north) and the last (south) ring."""
    nlat, nlon = p + 1, 2 * p
    j = np.arange(1, nlon - 1)
    north = np.stack([np.zeros_like(j), j, j + 1], 1)
    last = (nlat - 1) * nlon
    south = np.stack([np.full_like(j, last), last + j + 1, last + j], 1)
    return np.concatenate([north, ring_triangles(p), south]).astype(np.int64)


def mesh_arrays(n_vesicles, p):
    """triangles (N T1, 3) int64 on the N M points of a frame, vesicle_id (N M,) int32."""
    M = 2 * p * (p + 1)
    t = grid_triangles(p)
    off = np.arange(n_vesicles, dtype=np.int64) * M
    triangles = (t[None, :, :] + off[:, None, None]).reshape(-1, 3)
    return triangles, np.repeat(np.arange(n_vesicles, dtype=np.int32), M)


def write_mesh(f, n_vesicles, p):
    """Create /mesh/triangles and /mesh/vesicle_id in the open run file f if missing."""
    if "mesh" in f and "triangles" in f["mesh"] and "vesicle_id" in f["mesh"]:
        return
    triangles, vid = mesh_arrays(int(n_vesicles), int(p))
    g = f.require_group("mesh")
    for name, data, desc in (
            ("triangles", triangles, "triangles on the N M points of a frame (vesicle v: points [v M, (v+1) M)): "
             "latitude-ring quads split in two, polar caps as fans over their ring; counter-clockwise seen from "
             "outside (vesflow.io.xdmf)"),
            ("vesicle_id", vid, "the vesicle of each of the N M points of a frame")):
        if name in g:
            del g[name]
        g.create_dataset(name, data=data, compression="gzip", shuffle=True).attrs["description"] = desc


def _item(h5name, dataset, k, shape, number="Float", precision=8):
    """A HyperSlab DataItem: frame k of the dataset whose per-frame shape is `shape`, declared
    with k + 1 frames (datasets only grow or are rewritten along with this description).
    Its first child is a comment naming the frame: VTK's XDMF reader (ParaView's "Xdmf
    Reader") caches a grid's points keyed on the text of the geometry's first DataItem, so
    the key must differ between frames (and without any text it reports that it cannot cache)."""
    n = len(shape) + 1
    dims = " ".join(str(s) for s in shape)
    start = " ".join([str(k)] + ["0"] * (n - 1))
    ones = " ".join(["1"] * n)
    return (f'<DataItem ItemType="HyperSlab" Dimensions="1 {dims}" Type="HyperSlab"><!--{dataset} {k}-->'
            f'<DataItem Dimensions="3 {n}" Format="XML">{start} {ones} 1 {dims}</DataItem>'
            f'<DataItem Dimensions="{k + 1} {dims}" NumberType="{number}" Precision="{precision}" Format="HDF">'
            f'{h5name}:/frames/{dataset}</DataItem></DataItem>')


class XdmfFile:
    """Keeps PATH.xmf describing the frames of the open run file (h5py.File) it is synced with.

    sync(f) after every frame: appends the new frames' grids (the file is extended in place:
    the cost of a frame does not grow with the run), or rewrites the whole description
    (atomically) when frames were removed or replaced, the fields changed or the file on
    disk is not the one last written.
    """

    def __init__(self, xmf_path, h5_path):
        self.path = Path(xmf_path)
        self.h5name = os.path.relpath(Path(h5_path).resolve(), self.path.resolve().parent)
        self._chunks = []          # the XML of each frame's grid
        self._times = []
        self._head = None
        self._fields = None
        self._size = None          # bytes of the file as last written
        self._tail_text = None     # the end of the description as last written (_tail)

    @classmethod
    def beside(cls, h5_path):
        h5_path = Path(h5_path)
        return cls(h5_path.with_suffix(".xmf"), h5_path)

    def _header(self, f):
        a = f.attrs
        N, p = int(a["n_vesicles"]), int(a["p"])
        M = 2 * p * (p + 1)
        T = int(f["mesh/triangles"].shape[0])
        return N, M, T

    def _grid(self, k, t, shape, fields):
        N, M, T = shape
        h = self.h5name
        parts = [f'<Grid Name="frame {k}" GridType="Uniform"><Time Value="{t!r}"/>',
                 f'<Topology TopologyType="Triangle" NumberOfElements="{T}">'
                 f'<DataItem Dimensions="{T} 3" NumberType="Int" Precision="8" Format="HDF">{h}:/mesh/triangles'
                 f'</DataItem></Topology>',
                 f'<Geometry GeometryType="XYZ">{_item(h, "points", k, (N, M, 3))}</Geometry>']
        for name in fields:
            kind = POINT_FIELDS[name]
            shape_k = (N, M, 3) if kind == "Vector" else (N, M)
            parts.append(f'<Attribute Name="{name}" AttributeType="{kind}" Center="Node">'
                         f'{_item(h, name, k, shape_k)}</Attribute>')
        parts.append(f'<Attribute Name="vesicle_id" AttributeType="Scalar" Center="Node">'
                     f'<DataItem Dimensions="{N * M}" NumberType="Int" Precision="4" Format="HDF">'
                     f'{h}:/mesh/vesicle_id</DataItem></Attribute></Grid>\n')
        return "".join(parts)

    _TAIL = "</Grid>\n</Domain>\n</Xdmf>\n"

    def _tail(self, f):
        """The end of the description: the temporal collection closed, then (a run with a
        container, /wall) the wall's static grid, then the domain closed."""
        if "wall" not in f:
            return self._TAIL
        h, P, T = self.h5name, f["wall/points"].shape[0], f["wall/triangles"].shape[0]
        wall = (f'<Grid Name="wall" GridType="Uniform"><Topology TopologyType="Triangle" NumberOfElements="{T}">'
                f'<DataItem Dimensions="{T} 3" NumberType="Int" Precision="8" Format="HDF">{h}:/wall/triangles'
                f'</DataItem></Topology><Geometry GeometryType="XYZ"><DataItem Dimensions="{P} 3" NumberType="Float" '
                f'Precision="8" Format="HDF">{h}:/wall/points</DataItem></Geometry></Grid>\n')
        return "</Grid>\n" + wall + "</Domain>\n</Xdmf>\n"

    def sync(self, f):
        """Make the description match the frames of the open run file f."""
        fr = f["frames"]
        n = int(fr["time"].shape[0])
        fields = [name for name in POINT_FIELDS if name in fr]
        shape = self._header(f)
        head = ('<?xml version="1.0" ?>\n<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>\n<Xdmf Version="2.0">\n<Domain>\n'
                '<Grid Name="frames" GridType="Collection" CollectionType="Temporal">\n')
        times = [float(t) for t in fr["time"][:n]]
        on_disk = self._size is not None and self.path.exists() and self.path.stat().st_size == self._size
        tail = self._tail(f)
        keep = 0
        if fields == self._fields and head == self._head and on_disk and tail == self._tail_text:
            for old, new in zip(self._times, times):      # frames kept as they were
                if old != new:
                    break
                keep += 1
        self._head, self._fields, self._tail_text = head, fields, tail
        self._chunks = self._chunks[:keep] + [self._grid(k, times[k], shape, fields) for k in range(keep, n)]
        self._times = times
        if keep == 0:                      # rewrite: a reader never sees a partial file
            tmp = self.path.with_name(self.path.name + ".tmp")
            tmp.write_text(head + "".join(self._chunks) + tail)
            os.replace(tmp, self.path)
        else:                              # extend in place after the frames kept
            start = len(head) + sum(len(c) for c in self._chunks[:keep])
            with open(self.path, "r+") as fh:
                fh.seek(start)
                fh.write("".join(self._chunks[keep:]) + tail)
                fh.truncate()
        self._size = len(head) + sum(len(c) for c in self._chunks) + len(tail)


def write_xdmf(h5_path, xmf_path=None):
    """Write the XDMF description of a run file (default: RUN.xmf beside it); a file without
    /mesh (an earlier layout) gets it.  Returns the path written."""
    h5_path = Path(h5_path)
    with h5py.File(h5_path, "r") as f:
        has_mesh = "mesh" in f and "triangles" in f["mesh"] and "vesicle_id" in f["mesh"]
    if not has_mesh:
        with h5py.File(h5_path, "r+") as f:
            write_mesh(f, f.attrs["n_vesicles"], f.attrs["p"])
    x = XdmfFile(xmf_path or h5_path.with_suffix(".xmf"), h5_path)
    with h5py.File(h5_path, "r") as f:
        x.sync(f)
    return x.path

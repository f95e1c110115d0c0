"""Reading a run file: frames, steps, attributes, timings, checkpoint."""
from __future__ import annotations

import errno
from dataclasses import dataclass, field

import h5py
import numpy as np

from ..errors import SceneError
from .journal import FileInUse, recover, written_here
from .layout import STEP_REASONS


def open_run_file(path):
    """h5py.File(path, "r"), after rolling back a file that a killed run left mid-write
    (vesflow.io.journal.recover).  A file another process is writing is a SceneError."""
    if written_here(path):
        return h5py.File(path, "r", locking=False)
    try:
        recover(path)
        return h5py.File(path, "r")
    except FileInUse:
        raise SceneError(f"{path} is in use by another process") from None
    except OSError as e:
        if e.errno in (errno.EAGAIN, errno.EACCES) and "lock" in str(e):
            raise SceneError(f"{path} is in use by another process") from None
        raise


def _read_tree(g):
    out = {}
    for key, v in g.attrs.items():
        if key.startswith("_vesflow_"):
            continue
        if isinstance(v, h5py.Empty):
            out[key] = None
        elif isinstance(v, bytes):
            out[key] = v.decode()
        else:
            out[key] = v
    for key, v in g.items():
        if isinstance(v, h5py.Group):
            out[key] = _read_tree(v)
        elif v.attrs.get("vesflow_kind") == "str":
            out[key] = v.asstr()[...]
        else:
            out[key] = v[()]
    return out


def _checkpoint_name(f):
    """The group holding the latest complete checkpoint, or None."""
    best, best_t = None, -np.inf
    for name in ("checkpoint", "checkpoint_new"):
        if name in f and int(f[name].attrs.get("_vesflow_complete", 0)) == 1 and "time" in f[name].attrs:
            t = float(f[name].attrs["time"])
            if best is None or t > best_t:
                best, best_t = name, t
    return best


def read_attributes(path, what=None):
    """The root attributes of a run file as a dict (no datasets are read).  A missing file
    or one that is not a run file is a SceneError (prefixed by `what`, e.g. "--restart")."""
    pre = f"{what} {path}" if what else str(path)
    try:
        f = open_run_file(path)
    except FileNotFoundError:
        raise SceneError(f"{pre}: no such file") from None
    except OSError as e:
        raise SceneError(f"{pre}: cannot open it as an HDF5 file ({e})") from None
    with f:
        a = _attrs(f)
    missing = [k for k in ("scene", "p", "n_vesicles") if k not in a]
    if missing:
        raise SceneError(f"{pre}: not a vesflow run file (no root attribute {missing[0]!r})")
    return a


def read_checkpoint(path):
    """The latest complete checkpoint of a run file as a dict (arrays, scalars, nested
    dicts), with "time".  Raises SceneError if there is none."""
    with open_run_file(path) as f:
        name = _checkpoint_name(f)
        if name is None:
            raise SceneError(f"{path}: the file has no complete /checkpoint")
        return _read_tree(f[name])


@dataclass
class RunOutput:
    """What read_output returns: plain NumPy arrays and dicts."""

    path: str
    attrs: dict
    frames: dict                 # name -> array, first axis = the selected frames
    frame_index: np.ndarray      # indices in the file of the selected frames
    steps: dict                  # name -> array (one row per attempted step)
    timings: dict
    has_checkpoint: bool
    n_frames_total: int = 0
    reason_names: dict = field(default_factory=lambda: {c: n for c, (n, _) in STEP_REASONS.items()})

    @property
    def time(self):
        return self.frames["time"]

    @property
    def n_frames(self):
        return len(self.frame_index)

    @property
    def p(self):
        return int(self.attrs["p"])

    @property
    def n_vesicles(self):
        return int(self.attrs["n_vesicles"])

    @property
    def periodic_length(self):
        return float(self.attrs["periodic_length"])

    @property
    def restarts(self):
        return np.asarray(self.attrs.get("restarts", []), dtype=float)

    def unwrapped(self, name="points"):
        """A position field of the selected frames (points, coefficients or poles) with the
        lattice vectors that a periodic run's wrap took off added back (/frames/image); the
        field itself in free space."""
        a = np.array(self.frames[name], dtype=float)
        if "image" not in self.frames or self.periodic_length == 0.0:
            return a
        shift = self.periodic_length * np.asarray(self.frames["image"], dtype=float)      # (F, N, 3)
        if name == "coefficients":
            a[..., 0] += np.sqrt(4.0 * np.pi) * shift
        elif name in ("points", "poles"):
            a += shift[:, :, None, :]
        else:
            raise ValueError(f"unwrapped: {name!r} is not a position field (points, coefficients, poles)")
        return a

    def frame(self, i):
        """The i-th selected frame as a dict of arrays (optional fields included if present)."""
        return {k: v[i] for k, v in self.frames.items()}

    def __repr__(self):
        return (f"RunOutput({self.path!r}, p={self.p}, n_vesicles={self.n_vesicles}, "
                f"frames={self.n_frames}/{self.n_frames_total}, steps={len(self.steps.get('time', []))}, "
                f"fields={sorted(self.frames)})")


def _attrs(obj):
    out = {}
    for k, v in obj.attrs.items():
        if isinstance(v, bytes):
            v = v.decode()
        elif isinstance(v, np.ndarray) and v.dtype.kind == "O":
            v = [s.decode() if isinstance(s, bytes) else s for s in v.tolist()]
        out[k] = v
    return out


def _selection(n, frames):
    if frames is None:
        return np.arange(n), slice(None)
    if isinstance(frames, slice):
        idx = np.arange(n)[frames]
        if frames.step in (None, 1):
            return idx, slice(idx[0], idx[-1] + 1) if len(idx) else slice(0, 0)
        return idx, idx
    idx = np.atleast_1d(np.asarray(frames, dtype=np.int64))
    idx = np.where(idx < 0, idx + n, idx)
    if np.any((idx < 0) | (idx >= n)):
        raise IndexError(f"frame index out of range (the file has {n} frames)")
    return idx, idx


def _read_rows(d, sel):
    if isinstance(sel, slice):
        return d[sel]
    if len(sel) == 0:
        return np.empty((0,) + d.shape[1:], dtype=d.dtype)
    order = np.argsort(sel, kind="stable")
    uniq, inv = np.unique(sel[order], return_inverse=True)
    data = d[uniq]  # h5py needs increasing unique indices
    out = np.empty((len(sel),) + d.shape[1:], dtype=d.dtype)
    out[order] = data[inv]
    return out


def read_output(path, frames=None, fields=None):
    """Read a run file.  frames: None (all), a slice, or indices; fields: None (all of
    /frames) or names (time is always included).  Returns a RunOutput."""
    with open_run_file(path) as f:
        fr = f["frames"]
        n = int(fr["time"].shape[0])
        idx, sel = _selection(n, frames)
        names = list(fr) if fields is None else ["time"] + [x for x in fields if x != "time"]
        missing = [x for x in names if x not in fr]
        if missing:
            raise KeyError(f"{path}: no /frames/{missing[0]} (present: {sorted(fr)})")
        data = {name: _read_rows(fr[name], sel) for name in names}
        steps = {k: v[...] for k, v in f["steps"].items()} if "steps" in f else {}
        if "reason" in steps:
            steps["reason"] = steps["reason"].astype(np.int8)
        timings = _attrs(f["timings"]) if "timings" in f else {}
        return RunOutput(path=str(path), attrs=_attrs(f), frames=data, frame_index=idx, steps=steps,
                         timings=timings, has_checkpoint=_checkpoint_name(f) is not None,
                         n_frames_total=n)


def iter_frames(path, fields=None, frames=None):
    """Yield one dict per frame (keys: index, time and the requested /frames fields),
    reading one frame at a time from one open file."""
    with open_run_file(path) as f:
        fr = f["frames"]
        n = int(fr["time"].shape[0])
        idx, _ = _selection(n, frames)
        names = [x for x in (list(fr) if fields is None else fields) if x != "time"]
        for name in names:
            if name not in fr:
                raise KeyError(f"{path}: no /frames/{name} (present: {sorted(fr)})")
        for i in idx:
            out = {"index": int(i), "time": float(fr["time"][i])}
            for name in names:
                out[name] = fr[name][i]
            yield out


def frame_fields(path):
    """Names of the datasets under /frames of a run file."""
    with open_run_file(path) as f:
        return sorted(f["frames"])

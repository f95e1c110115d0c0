"""Writing a run file: frames, steps, timings, checkpoint; reopening it for a restart."""
from __future__ import annotations

import atexit
import errno
import functools
import json
import os
import weakref
from pathlib import Path

import h5py
import numpy as np

from ..errors import OutputError, SceneError
from .journal import FileInUse, JournaledFile
from .layout import (FIELD_DTYPES, FORMAT_VERSION, FRAME_FIELDS, OPTIONAL_FIELDS, REASON_CODE, STEP_COLUMNS, STEP_REASONS,
                     TIMING_KEYS, chunks, grid_size, now, time_tol)
from .reader import _checkpoint_name, _read_tree, read_checkpoint
from .xdmf import XdmfFile, grid_triangles, write_mesh


class _Failed(Exception):
    """A write of the file layer failed (OutputWriter._flush)."""


def _guarded(fn):
    """A writing method: after it, the file is flushed and committed (vesflow.io.journal); a
    failed write becomes OutputError (raised, or kept in `failure` with defer_errors), and
    once failed every writing method does nothing."""
    @functools.wraps(fn)
    def wrapper(self, *args, **kw):
        if self.failure is not None:
            return False
        try:
            return fn(self, *args, **kw)
        except Exception as e:
            if self._raw is None or self._raw.error is None:
                raise
            self.failure = self._output_error()
            if self.defer_errors:
                return False
            raise self.failure from (None if isinstance(e, _Failed) else e)
    return wrapper


_OPEN = weakref.WeakSet()    # writers whose file is open (closed at exit, see _close_open_writers)


@atexit.register
def _close_open_writers():
    """Close the files of writers nobody closed (e.g. after a failed write raised) while Python
    still runs: HDF5's own handler at process exit would call into the Python file layer after
    the interpreter has ended (a segmentation fault)."""
    for w in list(_OPEN):
        w.defer_errors = True
        try:
            w.close()
        except Exception:
            pass


class OutputWriter:
    """Writes one run file.  Use as a context manager or call close().

    OutputWriter(path, *, scene_text, options_text, version, p, n_vesicles,
                 periodic_length, restart_of=None, n_coefficients=None)
    creates (overwrites) the file; ``OutputWriter.reopen(path)`` continues one
    from its checkpoint.  The file is written through vesflow.io.journal.JournaledFile: it
    is locked while open (a second writer: SceneError "... is in use by another process"),
    and a failed write (no space left, an I/O error) puts it back to its state after the
    last complete operation and raises OutputError (with defer_errors: keeps it in
    `failure`; every later write does nothing).
    """

    def __init__(self, path, *, scene_text, options_text, version, p, n_vesicles,
                 periodic_length, restart_of=None, n_coefficients=None, checkpoint_every=None, _file=None):
        self.path = Path(path)
        self.checkpoint = None  # the state restarted from (reopen only)
        # write_checkpoint keeps at most one checkpoint per `checkpoint_every` of simulated
        # time (None: every call); `on_checkpoint` callables get each state written.
        self.checkpoint_every = None if checkpoint_every is None else float(checkpoint_every)
        self.last_checkpoint_time = None
        self.on_checkpoint = []
        self.failure = None          # the OutputError of a failed write
        self.defer_errors = False    # True: a failed write is kept in `failure`, not raised
        self._raw = None
        self._doing = "creating the file"
        self._committed = (0, None, None)    # frames, last frame time, checkpoint time on disk
        _OPEN.add(self)
        self.xdmf = XdmfFile.beside(self.path)  # RUN.xmf beside the file, synced at every frame
        if _file is not None:  # reopen()
            self._f, self._raw = _file
            self._read_sizes()
            ft = self._f["frames/time"]
            self._committed = (self.n_frames, float(ft[-1]) if self.n_frames else None, None)
            write_mesh(self._f, self.n_vesicles, self.p)   # a file of an earlier layout gets /mesh
            self._sync_xdmf()
            return
        p = int(p)
        n_vesicles = int(n_vesicles)
        if p < 1 or n_vesicles < 1:
            raise ValueError(f"OutputWriter: need p >= 1 and n_vesicles >= 1, got p={p}, n_vesicles={n_vesicles}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._raw = _open_layer(self.path, create=True)
        try:
            self._create(scene_text, options_text, version, p, n_vesicles, periodic_length, restart_of,
                         n_coefficients)
        except Exception as e:
            if self._raw.error is None:
                self._abandon()
                raise
            self.failure = self._output_error()
            self._abandon()
            raise self.failure from (None if isinstance(e, _Failed) else e)

    def _create(self, scene_text, options_text, version, p, n_vesicles, periodic_length, restart_of,
                n_coefficients):
        # libver v108: dense attribute storage (scene texts > 64 KiB) without the
        # v110 superblock whose "file open" flag would lock a file left by a killed run.
        f = h5py.File(self._raw, "w", libver=("v108", "latest"))
        self._f = f
        self.p, self.n_vesicles = p, n_vesicles
        self.M = grid_size(p)
        self.C = int(n_coefficients) if n_coefficients is not None else (p + 1) ** 2 - 1
        a = f.attrs
        a["vesflow_version"] = str(version)
        a["format_version"] = FORMAT_VERSION
        a["scene"] = str(scene_text or "")
        a["options"] = str(options_text or "")
        a["p"] = p
        a["n_vesicles"] = n_vesicles
        a["periodic_length"] = float(periodic_length or 0.0)
        a["n_grid_points"] = self.M
        a["n_coefficients"] = self.C
        a["grid"] = ("p-grid: nlat = p+1 Gauss-Legendre latitudes, cos(theta) descending (north first), "
                     "nlon = 2p longitudes phi_j = pi j / p, point index k = i * nlon + j")
        a["created"] = now()
        restarts = []
        a["restart_of"] = "" if restart_of is None else str(restart_of)
        if restart_of is not None:
            try:
                restarts.append(float(read_checkpoint(restart_of)["time"]))
            except Exception:  # the source may be gone: the path is still recorded
                pass
        a["restarts"] = np.asarray(restarts, dtype=float)
        a["restart_options"] = np.asarray([""] * len(restarts), dtype=h5py.string_dtype())

        fr = f.create_group("frames")
        for name, (shape_fn, desc, units, comp) in FRAME_FIELDS.items():
            self._create_frame_dataset(fr, name, shape_fn(n_vesicles, self.M, self.C), desc, units, comp)
        st = f.create_group("steps")
        for name, (dtype, desc) in STEP_COLUMNS.items():
            d = st.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(4096,))
            d.attrs["description"] = desc
        st["reason"].attrs["reason_table"] = json.dumps(
            {str(c): {"name": n, "meaning": m} for c, (n, m) in STEP_REASONS.items()})
        st.attrs["reason_table"] = st["reason"].attrs["reason_table"]
        tg = f.create_group("timings")
        for k in TIMING_KEYS:
            tg.attrs[k] = 0.0
        tg.attrs["units"] = "seconds (wall clock)"
        write_mesh(f, n_vesicles, p)
        self.n_frames = 0
        self.n_steps = 0
        self._flush()

    def _abandon(self):
        """Close the handles of a file that could not be created (no rollback needed: the
        file is new)."""
        try:
            if getattr(self, "_f", None) is not None and self._f.id.valid:
                self._f.close()
        finally:
            self._raw.close()

    def _flush(self):
        """Flush HDF5's caches; the file is then consistent and the journal is emptied."""
        self._f.flush()
        if self._raw.error is None:
            self._raw.commit()
        if self._raw.error is not None:
            raise _Failed()
        self._committed = (self.n_frames, self._last_frame_time(), self.last_checkpoint_time)

    def _sync_xdmf(self):
        """RUN.xmf to the frames on disk; a failed write of it is an OutputError as the run
        file's are (the run file itself is complete: `vesflow export` writes RUN.xmf again)."""
        try:
            self.xdmf.sync(self._f)
        except OSError as e:
            cause = (os.strerror(e.errno) if e.errno else str(e)).lower().rstrip(".")
            self.failure = OutputError(f"{self.xdmf.path}: {cause} (writing the XDMF description); {self.path} "
                                       f"is complete: vesflow export {self.path} writes the description again")
            if not self.defer_errors:
                raise self.failure

    def _last_frame_time(self):
        return float(self._f["frames/time"][self.n_frames - 1]) if self.n_frames else None

    def _output_error(self):
        """The OutputError of the failed write: the file, the cause, what is on disk now."""
        e = self._raw.error
        cause = (os.strerror(e.errno) if e.errno else str(e)).lower().rstrip(".")
        n, tf, tc = self._committed
        held = (f"{n} frame{'s' if n > 1 else ''} up to t = {tf:.6g}" if n else "no frame") + (
            f" and the checkpoint at t = {tc:.6g}" if tc is not None else "")
        if self._raw.rollback_error is not None:
            state = (f"it could not be put back to its last complete frame ({self._raw.rollback_error.strerror}): "
                     f"any vesflow command reading it will")
        else:
            state = f"the file holds {held}"
        when = " once there is space" if e.errno in (errno.ENOSPC, errno.EDQUOT) else ""
        more = f": vesflow run --restart {self.path} continues it{when}" if tc is not None else ""
        return OutputError(f"{self.path}: {cause} ({self._doing}); {state}{more}")

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def _create_frame_dataset(group, name, shape, desc, units, compressed, fill=None):
        kw = dict(compression="gzip", compression_opts=4, shuffle=True) if compressed else {}
        dtype, int_fill = FIELD_DTYPES.get(name, ("f8", None))
        if fill is not None:
            kw["fillvalue"] = fill if int_fill is None else int_fill
        d = group.create_dataset(name, shape=(0,) + tuple(shape), maxshape=(None,) + tuple(shape),
                                 dtype=dtype, chunks=chunks(shape, compressed), **kw)
        d.attrs["description"] = desc
        d.attrs["units"] = units
        return d

    def _read_sizes(self):
        a = self._f.attrs
        self.p = int(a["p"])
        self.n_vesicles = int(a["n_vesicles"])
        self.M = int(a.get("n_grid_points", grid_size(self.p)))
        self.C = int(a.get("n_coefficients", (self.p + 1) ** 2 - 1))
        self.n_frames = int(self._f["frames/time"].shape[0])
        self.n_steps = int(self._f["steps/time"].shape[0])

    def _check(self, name, arr, shape):
        a = np.asarray(arr, dtype=FIELD_DTYPES.get(name, ("f8",))[0])
        if a.shape != tuple(shape):
            raise ValueError(f"write_frame: {name} has shape {a.shape}, expected {tuple(shape)} "
                             f"(N={self.n_vesicles}, M={self.M}, C={self.C})")
        return a

    # ------------------------------------------------------------------ writing
    @_guarded
    def write_frame(self, time, points, coefficients, tension, area, volume, centroid,
                    bending_energy, velocity=None, poles=None, image=None, bending_energy_density=None):
        """Append one frame and flush.  Shapes: points (N, M, 3), coefficients (N, 3, C),
        tension (N, M), area/volume/bending_energy (N,), centroid (N, 3), velocity
        (N, M, 3) optional, poles (N, 2, 3) optional (north, south), image (N, 3) integers
        optional (periodic runs), bending_energy_density (N, M) optional.  Returns the frame index."""
        N, M, C = self.n_vesicles, self.M, self.C
        self._doing = f"writing frame {self.n_frames} at t = {float(time):.6g}"
        values = {"time": np.float64(time)}
        given = dict(points=points, coefficients=coefficients, tension=tension, area=area, volume=volume,
                     centroid=centroid, bending_energy=bending_energy)
        for name, arr in given.items():
            values[name] = self._check(name, arr, FRAME_FIELDS[name][0](N, M, C))
        optional = {}
        for name, arr in (("velocity", velocity), ("poles", poles), ("image", image),
                          ("bending_energy_density", bending_energy_density)):
            if arr is not None:
                optional[name] = self._check(name, arr, OPTIONAL_FIELDS[name][0](N, M, C))
        fr = self._f["frames"]
        k = self.n_frames
        if k > 0 and abs(float(fr["time"][k - 1]) - float(time)) <= time_tol(time):
            k -= 1  # a frame at the time of the last one replaces it (frame times increase strictly)
        for name, v in values.items():
            d = fr[name]
            d.resize(k + 1, axis=0)
            d[k] = v
        for name, (shape_fn, desc, units, comp) in OPTIONAL_FIELDS.items():
            if name not in fr and name not in optional:
                continue
            if name not in fr:  # first time: earlier frames read back as NaN
                self._create_frame_dataset(fr, name, shape_fn(N, M, C), desc, units, comp, fill=np.nan)
            d = fr[name]
            d.resize(k + 1, axis=0)
            if name in optional:
                d[k] = optional[name]
            else:
                d[k] = FIELD_DTYPES.get(name, (None, np.nan))[1]
        self.n_frames = k + 1
        self._flush()
        self._sync_xdmf()
        return k

    @_guarded
    def write_steps(self, rows):
        """Append attempted steps and flush.  rows: a sequence of mappings (keys of
        STEP_COLUMNS), or of tuples in the order time, dt, accepted, ksp_its,
        error_estimate, reason, q_self, q_near, or one mapping of equal-length columns.
        reason is a code or a name of STEP_REASONS; missing columns: accepted=1, ksp_its=0,
        error_estimate=NaN, reason=accepted if accepted else other, q_self=q_near=0."""
        names = list(STEP_COLUMNS)
        if isinstance(rows, dict):
            cols = {k: np.atleast_1d(np.asarray(v)) for k, v in rows.items()}
            n = len(cols.get("time", []))
            if any(len(v) != n for v in cols.values()):
                raise ValueError("write_steps: columns of different lengths")
        else:
            rows = list(rows)
            n = len(rows)
            cols = {k: [] for k in names}
            for r in rows:
                if isinstance(r, dict):
                    unknown = set(r) - set(names)
                    if unknown:
                        raise ValueError(f"write_steps: unknown column(s) {sorted(unknown)}; known: {names}")
                    for k in names:
                        cols[k].append(r.get(k))
                else:
                    r = tuple(r)
                    if not 2 <= len(r) <= len(names):
                        raise ValueError(f"write_steps: a row has {len(r)} values, expected 2..{len(names)}")
                    for i, k in enumerate(names):
                        cols[k].append(r[i] if i < len(r) else None)
        if n == 0:
            return
        if "time" not in cols or "dt" not in cols or any(v is None for v in cols["time"]) \
                or any(v is None for v in cols["dt"]):
            raise ValueError("write_steps: every row needs time and dt")
        time = np.asarray(cols["time"], dtype="f8")
        dt = np.asarray(cols["dt"], dtype="f8")
        acc = [1 if v is None else int(bool(v)) for v in cols.get("accepted", [None] * n)]
        its = [0 if v is None else int(v) for v in cols.get("ksp_its", [None] * n)]
        err = [np.nan if v is None else float(v) for v in cols.get("error_estimate", [None] * n)]
        reason = []
        for a, v in zip(acc, cols.get("reason", [None] * n)):
            if v is None:
                reason.append(0 if a else -1)
            elif isinstance(v, (str, bytes)):
                name = v.decode() if isinstance(v, bytes) else v
                if name not in REASON_CODE:
                    raise ValueError(f"write_steps: unknown reason {name!r}; known: {sorted(REASON_CODE)}")
                reason.append(REASON_CODE[name])
            else:
                if int(v) not in STEP_REASONS:
                    raise ValueError(f"write_steps: unknown reason code {v!r}; known: {sorted(STEP_REASONS)}")
                reason.append(int(v))
        qs = [0 if v is None else int(v) for v in cols.get("q_self", [None] * n)]
        qn = [0 if v is None else int(v) for v in cols.get("q_near", [None] * n)]
        data = dict(time=time, dt=dt, accepted=np.asarray(acc, "i1"), ksp_its=np.asarray(its, "i4"),
                    error_estimate=np.asarray(err, "f8"), reason=np.asarray(reason, "i1"),
                    q_self=np.asarray(qs, "i2"), q_near=np.asarray(qn, "i2"))
        self._doing = "writing the steps"
        st = self._f["steps"]
        k = self.n_steps
        for name in names:
            if name not in st:                    # a file of an older layout, reopened for a restart
                dtype, desc = STEP_COLUMNS[name]
                st.create_dataset(name, data=np.zeros(k, dtype), maxshape=(None,), chunks=(4096,))
                st[name].attrs["description"] = desc
            d = st[name]
            d.resize(k + n, axis=0)
            d[k:k + n] = data[name]
        self.n_steps = k + n
        self._flush()

    @_guarded
    def write_timings(self, timings):
        """Set /timings attributes (seconds) from a dict; known keys: setup, self, near,
        far, repar, other, total; other keys are stored as well."""
        self._doing = "writing the timings"
        tg = self._f["timings"]
        for k, v in dict(timings).items():
            tg.attrs[str(k)] = float(v)
        self._flush()

    def checkpoint_due(self, time):
        """True if a checkpoint at simulated time `time` is due under checkpoint_every."""
        if self.checkpoint_every is None or self.last_checkpoint_time is None:
            return True
        t = float(time)
        return t >= self.last_checkpoint_time + self.checkpoint_every - time_tol(t)

    @_guarded
    def write_checkpoint(self, state, force=False):
        """Replace /checkpoint by `state` (a dict with at least "time"): arrays become
        datasets, scalars and strings attributes, nested dicts groups, None an empty
        attribute.  Written to /checkpoint_new first, then swapped in.  Skipped (returns
        False) when the last checkpoint is less than checkpoint_every older, unless force.
        After writing, every callable of `on_checkpoint` is called with the state."""
        if "time" not in state:
            raise ValueError("write_checkpoint: the state needs a 'time' entry")
        if not force and not self.checkpoint_due(state["time"]):
            return False
        f = self._f
        self._doing = f"writing the checkpoint at t = {float(state['time']):.6g}"
        if "checkpoint_new" in f:
            del f["checkpoint_new"]
        g = f.create_group("checkpoint_new")
        _write_tree(g, state)
        g.attrs["_vesflow_n_frames"] = self.n_frames
        g.attrs["_vesflow_n_steps"] = self.n_steps
        g.attrs["_vesflow_written"] = now()
        g.attrs["_vesflow_complete"] = 1  # last: a group without it is never used
        self._flush()
        if "checkpoint" in f:
            del f["checkpoint"]
        f.move("checkpoint_new", "checkpoint")
        self.last_checkpoint_time = float(state["time"])
        self._flush()
        for fn in list(self.on_checkpoint):
            fn(state)
        return True

    @_guarded
    def write_wall(self, points, coefficients, p):
        """The container's wall, once (it does not move): /wall/points (M_w, 3) on its p_w-grid,
        /wall/triangles (as /mesh/triangles for one surface, vesflow.io.xdmf.grid_triangles),
        /wall/coefficients (3, C_w) and the attribute p."""
        self._doing = "writing the wall"
        if "wall" in self._f:
            del self._f["wall"]
        g = self._f.create_group("wall")
        g.attrs["p"] = int(p)
        g.attrs["description"] = "the closed container ([wall]): fixed, no-slip (docs/explanation/walls.md)"
        for name, data, desc in (
                ("points", np.asarray(points, dtype=float), "the wall's p_w-grid points (grid order)"),
                ("triangles", grid_triangles(int(p)), "triangles on the wall's points, counter-clockwise seen "
                                                       "from outside"),
                ("coefficients", np.asarray(coefficients, dtype=float), "the wall's position coefficients (3, C_w)")):
            g.create_dataset(name, data=data).attrs["description"] = desc
        self._flush()

    @_guarded
    def write_attrs(self, **attrs):
        """Set extra root attributes (strings or numbers) and flush."""
        self._doing = "writing attributes"
        for k, v in attrs.items():
            self._f.attrs[str(k)] = v
        self._flush()

    # ------------------------------------------------------------------ restart
    @classmethod
    def reopen(cls, path, *, options_text=None, checkpoint_every=None, restart_of=None):
        """Open an existing run file to continue it from its checkpoint: frames with
        time > t_checkpoint and steps that start at or after t_checkpoint are removed,
        t_checkpoint is appended to the root attribute `restarts` (and options_text,
        or "", to `restart_options`).  Returns the writer; the checkpoint state (a dict,
        as read_checkpoint returns it) is its attribute `checkpoint`."""
        path = Path(path)
        if not path.exists():
            raise SceneError(f"--restart {path}: no such file")
        raw = _open_layer(path, what="--restart")
        try:
            f = h5py.File(raw, "r+")
        except OSError as e:
            raw.close()
            raise SceneError(f"--restart {path}: cannot open it as an HDF5 file ({e})") from None
        try:
            name = _checkpoint_name(f)
            if name is None:
                raise SceneError(f"--restart {path}: the file has no complete /checkpoint to restart from")
            if name != "checkpoint":  # killed between delete and move: finish the move
                if "checkpoint" in f:
                    del f["checkpoint"]
                f.move(name, "checkpoint")
            elif "checkpoint_new" in f:  # an unfinished newer checkpoint
                del f["checkpoint_new"]
            state = _read_tree(f["checkpoint"])
            tc = float(state["time"])
            tol = time_tol(tc)
            ft = f["frames/time"][...]
            keep_f = int(np.argmax(ft > tc + tol)) if np.any(ft > tc + tol) else len(ft)
            for d in f["frames"].values():
                d.resize(keep_f, axis=0)
            stt = f["steps/time"][...]
            keep_s = int(np.argmax(stt >= tc - tol)) if np.any(stt >= tc - tol) else len(stt)
            for d in f["steps"].values():
                d.resize(keep_s, axis=0)
            a = f.attrs
            a["restarts"] = np.append(np.asarray(a.get("restarts", []), dtype=float), tc)
            old = [s.decode() if isinstance(s, bytes) else str(s) for s in a.get("restart_options", [])]
            a["restart_options"] = np.asarray(old + [str(options_text or "")], dtype=h5py.string_dtype())
            if restart_of is not None and Path(restart_of).resolve() != path.resolve():
                a["restart_of"] = str(restart_of)
            f.flush()
            if raw.error is not None:
                raise OutputError(f"{path}: {os.strerror(raw.error.errno).lower()} (reopening it for the restart); "
                                  f"the file is unchanged")
            raw.commit()
        except BaseException:
            f.close()
            raw.close()
            raise
        w = cls(path, scene_text=None, options_text=None, version=None, p=None, n_vesicles=None,
                periodic_length=None, checkpoint_every=checkpoint_every, _file=(f, raw))
        w.checkpoint = state
        w.last_checkpoint_time = tc
        w._committed = w._committed[:2] + (tc,)
        return w

    # ------------------------------------------------------------------ closing
    @_guarded
    def flush(self):
        self._doing = "flushing it"
        self._flush()

    def close(self):
        """Flush, close and unlock the file.  A failed last flush becomes `failure` (raised
        unless defer_errors or an earlier failure)."""
        if self._f is None:
            return
        earlier = self.failure
        try:
            if self._f.id.valid:
                try:
                    if earlier is None:
                        self.flush()
                finally:                 # closed even when the flush failed: no HDF5 file left open
                    self._doing = "closing it"
                    self._f.close()
        finally:
            self._raw.close()
            self._f = None
            _OPEN.discard(self)
        if self.failure is None and self._raw.error is not None:     # HDF5's last writes, at the close
            self.failure = self._output_error()
            if not self.defer_errors:
                raise self.failure

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _open_layer(path, create=False, what=None):
    """The JournaledFile of a run file; another process holding it is a SceneError."""
    try:
        return JournaledFile(path, create=create)
    except FileInUse as e:
        raise SceneError(f"{what} {e.strerror}" if what else e.strerror) from None
    except OSError as e:
        pre = f"{what} {path}" if what else str(path)
        raise OutputError(f"{pre}: {(e.strerror or str(e)).lower()} (opening it for writing)") from None


def _write_tree(g, state):
    for key, v in state.items():
        key = str(key)
        if isinstance(v, dict):
            _write_tree(g.create_group(key), v)
        elif v is None:
            g.attrs[key] = h5py.Empty("f8")
        elif isinstance(v, (str, bytes)):
            g.attrs[key] = v
        elif isinstance(v, (bool, int, float, complex, np.generic)) or (
                isinstance(v, np.ndarray) and v.ndim == 0):
            g.attrs[key] = v
        else:
            a = np.asarray(v)
            if a.dtype.kind == "U":
                d = g.create_dataset(key, data=a.astype(object), dtype=h5py.string_dtype())
                d.attrs["vesflow_kind"] = "str"
            elif a.dtype.kind == "O":
                raise TypeError(f"write_checkpoint: cannot store {key!r} of type {type(v).__name__}")
            else:
                g.create_dataset(key, data=a)

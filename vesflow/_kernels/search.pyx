# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Cell-list near search (docs/explanation/method.md, section 5.2: near pairs by a spatial sort, 27-neighbour search).

:func:`near_pairs` finds every (target, source vesicle) pair with the target within a
distance ``h`` of at least one source point of that vesicle (other vesicles only).

Cells: cubes of side ``h (1 + 1e-12)`` (the tiny margin makes "distance <= h implies
neighbouring cells" hold in floating point too).  Only the occupied cells are stored: each
source gets its integer cell coordinates ``(ix, iy, iz)`` (int64 each), the sources are
sorted lexicographically by cell and a target looks up its 27 neighbouring cells by binary
search.  Memory is O(#sources), whatever the size or sparsity of the domain (no dense
grid, no combined key that could overflow).

:func:`coincident_sources` is the helper of the FMM far field (vesflow/layerpot/far.py):
for each target, the nearest source of its own vesicle if it lies within a tolerance.
"""
import numpy as np

from cython.parallel cimport prange, parallel
from libc.math cimport floor, sqrt, INFINITY
from libc.stdlib cimport calloc, free, realloc
cimport openmp


ctypedef struct _Buf:
    # per-thread growable list of (vesicle, squared distance); targets own contiguous segments
    long* v
    double* d
    Py_ssize_t n
    Py_ssize_t cap
    int fail


cdef int _grow(_Buf* b) noexcept nogil:
    cdef Py_ssize_t cap = 2 * b.cap if b.cap > 0 else 1024
    cdef long* v = <long*> realloc(b.v, cap * sizeof(long))
    if v == NULL:
        b.fail = 1
        return -1
    b.v = v
    cdef double* d = <double*> realloc(b.d, cap * sizeof(double))
    if d == NULL:
        b.fail = 1
        return -1
    b.d = d
    b.cap = cap
    return 0


cdef inline Py_ssize_t _find_cell(const long* cells, Py_ssize_t n, long ix, long iy, long iz) noexcept nogil:
    """Index of cell (ix, iy, iz) in the lexicographically sorted (n, 3) cell list, or -1."""
    cdef Py_ssize_t lo = 0, hi = n, mid
    cdef const long* c
    while lo < hi:
        mid = (lo + hi) >> 1
        c = cells + 3 * mid
        if c[0] < ix or (c[0] == ix and (c[1] < iy or (c[1] == iy and c[2] < iz))):
            lo = mid + 1
        else:
            hi = mid
    if lo < n and cells[3 * lo] == ix and cells[3 * lo + 1] == iy and cells[3 * lo + 2] == iz:
        return lo
    return -1


cdef void _one_target(const double* x, long tv,
                      const double* src, const long* src_id,
                      const long* order, const long* cells, const long* cell_start, Py_ssize_t ncell,
                      const double* o, double hc, long nx, long ny, long nz, double h2,
                      _Buf* b, long* pos, long* cnt) noexcept nogil:
    """Append the (vesicle, min d^2) list of one target to its thread buffer, sorted by vesicle."""
    cdef Py_ssize_t start = b.n, j, k, c
    cdef long cx, cy, cz, ix, iy, iz, s, v, vk
    cdef double fx, fy, fz, r0, r1, r2, d2, dk
    cdef int found
    pos[0] = start
    cnt[0] = 0
    fx = floor((x[0] - o[0]) / hc)
    fy = floor((x[1] - o[1]) / hc)
    fz = floor((x[2] - o[2]) / hc)
    # targets more than one cell outside the sources' box have no near source (NaN too)
    if not (fx >= -1.0 and fx <= <double> nx and fy >= -1.0 and fy <= <double> ny
            and fz >= -1.0 and fz <= <double> nz):
        return
    cx = <long> fx
    cy = <long> fy
    cz = <long> fz
    for ix in range(cx - 1, cx + 2):
        if ix < 0 or ix >= nx:
            continue
        for iy in range(cy - 1, cy + 2):
            if iy < 0 or iy >= ny:
                continue
            for iz in range(cz - 1, cz + 2):
                if iz < 0 or iz >= nz:
                    continue
                c = _find_cell(cells, ncell, ix, iy, iz)
                if c < 0:
                    continue
                for j in range(cell_start[c], cell_start[c + 1]):
                    s = order[j]
                    v = src_id[s]
                    if v == tv:
                        continue
                    r0 = x[0] - src[3 * s]
                    r1 = x[1] - src[3 * s + 1]
                    r2 = x[2] - src[3 * s + 2]
                    d2 = r0 * r0 + r1 * r1 + r2 * r2
                    if d2 > h2:
                        continue
                    found = 0
                    for k in range(start, b.n):
                        if b.v[k] == v:
                            if d2 < b.d[k]:
                                b.d[k] = d2
                            found = 1
                            break
                    if not found:
                        if b.n == b.cap and _grow(b) != 0:
                            return
                        b.v[b.n] = v
                        b.d[b.n] = d2
                        b.n += 1
    # insertion sort of this target's segment by vesicle id (a handful of entries)
    for j in range(start + 1, b.n):
        vk = b.v[j]
        dk = b.d[j]
        k = j - 1
        while k >= start and b.v[k] > vk:
            b.v[k + 1] = b.v[k]
            b.d[k + 1] = b.d[k]
            k -= 1
        b.v[k + 1] = vk
        b.d[k + 1] = dk
    cnt[0] = b.n - start


def near_pairs(const double[:, ::1] trg, const long[::1] trg_id,
               const double[:, ::1] src, const long[::1] src_id, double h):
    """Near (target, source vesicle) pairs within distance h (docs/explanation/method.md, section 5.2).

    Returns ``(pairs, dist)``: ``pairs`` int64 (P, 2) of ``(target index, source vesicle id)``
    with ``src_id[s] != trg_id[t]`` and ``|trg_t - src_s| <= h`` for at least one source s
    of that vesicle, each pair once, sorted by (target, vesicle); ``dist`` float64 (P,) the
    minimum such distance.  Vesicle ids are the values of ``src_id`` (any int64).
    Cost O((T + S) log S) plus the points in the 27 neighbouring cells of each target.
    """
    if trg.shape[1] != 3 or src.shape[1] != 3:
        raise ValueError(f"trg and src must have shape (n, 3), got ({trg.shape[0]}, {trg.shape[1]}) and ({src.shape[0]}, {src.shape[1]})")
    if trg_id.shape[0] != trg.shape[0]:
        raise ValueError(f"trg_id has length {trg_id.shape[0]}, trg has {trg.shape[0]} points")
    if src_id.shape[0] != src.shape[0]:
        raise ValueError(f"src_id has length {src_id.shape[0]}, src has {src.shape[0]} points")
    if not (h > 0.0 and h < float("inf")):
        raise ValueError(f"near_pairs: h must be positive and finite, got {h}")
    cdef Py_ssize_t nt = trg.shape[0], ns = src.shape[0]
    if nt == 0 or ns == 0:
        return np.empty((0, 2), dtype=np.int64), np.empty(0, dtype=np.float64)

    src_np = np.asarray(src)
    if not np.all(np.isfinite(src_np)):
        raise ValueError("near_pairs: source points must be finite")
    cdef double hc = h * (1.0 + 1e-12)
    o_np = np.ascontiguousarray(src_np.min(axis=0))
    ext = (src_np.max(axis=0) - o_np) / hc
    if np.max(ext) >= 2.0**60:
        raise ValueError(f"near_pairs: the source cloud spans {np.max(ext):.3g} cells of size h = {h}; "
                         "cell coordinates would overflow int64")
    cells = np.floor((src_np - o_np) / hc).astype(np.int64)
    nxyz = cells.max(axis=0) + 1
    order_np = np.lexsort((cells[:, 2], cells[:, 1], cells[:, 0])).astype(np.int64)
    sc = cells[order_np]
    new = np.ones(ns, dtype=bool)
    new[1:] = np.any(sc[1:] != sc[:ns - 1], axis=1)
    cstart_np = np.append(np.flatnonzero(new), ns).astype(np.int64)
    ccells_np = np.ascontiguousarray(sc[new], dtype=np.int64)

    cdef const long[::1] order = order_np
    cdef const long[:, ::1] ccells = ccells_np
    cdef const long[::1] cstart = cstart_np
    cdef const double[::1] o = o_np
    cdef long nx = nxyz[0], ny = nxyz[1], nz = nxyz[2]
    cdef Py_ssize_t ncell = ccells_np.shape[0]
    cdef double h2 = h * h

    pos_np = np.zeros(nt, dtype=np.int64)
    cnt_np = np.zeros(nt, dtype=np.int64)
    tid_np = np.zeros(nt, dtype=np.int64)
    cdef long[::1] pos = pos_np
    cdef long[::1] cnt = cnt_np
    cdef long[::1] ttid = tid_np

    cdef int nth = openmp.omp_get_max_threads()
    cdef _Buf* bufs = <_Buf*> calloc(nth, sizeof(_Buf))
    if bufs == NULL:
        raise MemoryError("near_pairs: cannot allocate the thread buffers")
    cdef Py_ssize_t t, k, q, P
    cdef int tid = 0, i
    cdef const double* ptrg = &trg[0, 0]
    cdef const double* psrc = &src[0, 0]
    cdef const long* pid = &src_id[0]
    try:
        with nogil, parallel(num_threads=nth):
            tid = openmp.omp_get_thread_num()
            for t in prange(nt, schedule="dynamic", chunksize=64):
                ttid[t] = tid
                _one_target(ptrg + 3 * t, trg_id[t], psrc, pid,
                            &order[0], &ccells[0, 0], &cstart[0], ncell,
                            &o[0], hc, nx, ny, nz, h2,
                            &bufs[tid], &pos[t], &cnt[t])
        for i in range(nth):
            if bufs[i].fail:
                raise MemoryError("near_pairs: out of memory for the pair list")
        off_np = np.zeros(nt + 1, dtype=np.int64)
        np.cumsum(cnt_np, out=off_np[1:])
        P = off_np[nt]
        pairs_np = np.empty((P, 2), dtype=np.int64)
        dist_np = np.empty(P, dtype=np.float64)
        if P > 0:
            _gather(pairs_np, dist_np, off_np, pos, cnt, ttid, bufs)
        return pairs_np, dist_np
    finally:
        for i in range(nth):
            free(bufs[i].v)
            free(bufs[i].d)
        free(bufs)


cdef void _gather(long[:, ::1] pairs, double[::1] dist, const long[::1] off,
                  const long[::1] pos, const long[::1] cnt, const long[::1] ttid,
                  _Buf* bufs) noexcept:
    cdef Py_ssize_t t, k, q, nt = pos.shape[0]
    cdef _Buf* b
    with nogil:
        for t in range(nt):
            b = &bufs[ttid[t]]
            q = off[t]
            for k in range(cnt[t]):
                pairs[q + k, 0] = t
                pairs[q + k, 1] = b.v[pos[t] + k]
                dist[q + k] = sqrt(b.d[pos[t] + k])


def coincident_sources(const double[:, ::1] src, const long[::1] src_off,
                       const double[:, ::1] trg, const long[::1] trg_vi, double tol):
    """For each target t with ``v = trg_vi[t] >= 0``: index of the nearest source of vesicle v
    (range ``src_off[v]:src_off[v+1]``) if it lies within distance ``tol``, else -1.

    Used by the FMM far field to snap targets that coincide with a source of their own
    vesicle up to rounding onto that source exactly (see vesflow/layerpot/far.py).
    Returns an int64 array (T,).  Cost O(T M), M sources per vesicle.
    """
    if src.shape[1] != 3 or trg.shape[1] != 3:
        raise ValueError("src and trg must have shape (n, 3)")
    if trg_vi.shape[0] != trg.shape[0]:
        raise ValueError(f"trg_vi has length {trg_vi.shape[0]}, trg has {trg.shape[0]} points")
    cdef Py_ssize_t nt = trg.shape[0], nv = src_off.shape[0] - 1
    if nv < 0 or (nv > 0 and (src_off[0] < 0 or src_off[nv] > src.shape[0])):
        raise ValueError("src_off must hold V + 1 offsets into src")
    res_np = np.full(nt, -1, dtype=np.int64)
    if nt == 0:
        return res_np
    vi_np = np.asarray(trg_vi)
    if vi_np.size and vi_np.max() >= nv:
        raise IndexError(f"trg_vi has a vesicle index >= {nv} (number of vesicles)")
    cdef long[::1] res = res_np
    cdef Py_ssize_t t, s, best
    cdef long v
    cdef double r0, r1, r2, d2, dbest, tol2 = tol * tol
    with nogil:
        for t in prange(nt, schedule="static"):
            v = trg_vi[t]
            if v < 0:
                continue
            best = -1
            dbest = tol2
            for s in range(src_off[v], src_off[v + 1]):
                r0 = trg[t, 0] - src[s, 0]
                r1 = trg[t, 1] - src[s, 1]
                r2 = trg[t, 2] - src[s, 2]
                d2 = r0 * r0 + r1 * r1 + r2 * r2
                if d2 <= dbest:
                    dbest = d2
                    best = s
            res[t] = best
    return res_np


def nearest_sources(const double[:, ::1] src, const long[::1] src_off, const long[::1] rows,
                    const double[:, ::1] x, long[::1] index, double[::1] dist2):
    """For each point x[i] (P, 3) its nearest source of vesicle rows[i] (sources src_off[v] ..
    src_off[v+1] of src (n, 3)): index[i] the source's position within the vesicle (the first
    of equally near ones), dist2[i] the squared distance.  The start of the projections."""
    cdef Py_ssize_t P = x.shape[0], nv = src_off.shape[0] - 1, i, s, s0, s1, best
    if x.shape[1] != 3 or src.shape[1] != 3:
        raise ValueError("nearest_sources: src (n, 3) and x (P, 3) expected")
    if rows.shape[0] != P or index.shape[0] != P or dist2.shape[0] != P:
        raise ValueError("nearest_sources: rows, index and dist2 must have one entry per point")
    for i in range(P):
        if not (0 <= rows[i] < nv) or src_off[rows[i] + 1] <= src_off[rows[i]] or src_off[rows[i] + 1] > src.shape[0]:
            raise ValueError(f"nearest_sources: rows[{i}] = {rows[i]} is not a vesicle with sources in [0, {nv})")
    cdef double d0, d1, d2, dd, lo
    with nogil:
        for i in prange(P, schedule="static"):
            s0 = src_off[rows[i]]
            s1 = src_off[rows[i] + 1]
            best = s0
            lo = INFINITY
            for s in range(s0, s1):
                d0 = src[s, 0] - x[i, 0]
                d1 = src[s, 1] - x[i, 1]
                d2 = src[s, 2] - x[i, 2]
                dd = d0 * d0 + d1 * d1 + d2 * d2
                if dd < lo:
                    lo = dd
                    best = s
            index[i] = best - s0
            dist2[i] = lo

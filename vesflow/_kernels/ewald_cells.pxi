# The real-space part of vesflow._kernels.ewald (textually included by ewald.pyx: one compiled
# module; this file holds its cell-list sum).
# ---------------------------------------------------------------------------------------
# The real-space sum with its cell structure built ONCE per geometry (a GMRES solve applies it
# with new densities every iteration): sources and targets sorted by cell, sources stored
# contiguously in cell order (wrapped positions), the periodic image shift of each neighbour
# cell computed per cell instead of a minimum image per pair.
# ---------------------------------------------------------------------------------------
ctypedef struct _Cells:
    long n[3]
    double L[3]
    double lo[3]              # the box's corner and the cells' sides (neighbour-cell culling)
    double side[3]
    bint periodic
    bint mi_any
    double mL[3]              # L on an axis of fewer than 2 SUB + 1 cells (minimum image per pair), else 0
    double iL[3]
    double rc2
    double rc2_cull           # rc^2 with a relative margin: a cell is skipped when farther than this
    double xi
    Py_ssize_t ld             # leading dimension of the source columns (>= S + VF_BLOCK)
    const double* ys          # wrapped source positions, cell order, 3 columns of ld
    const double* dens        # densities in cell order, columns of ld: f (3), nw, g (3 + 3)
    const long* cstart        # sources of cell c: cstart[c] .. cstart[c + 1]
    const long* crun          # runs (one vesicle's sources in one cell) of cell c: crun[c] .. crun[c + 1]
    const long* rstart        # sources of run r: rstart[r] .. rstart[r + 1]
    const long* rvi           # vesicle index of run r
    const long* tstart        # targets (cell order) of cell c: tstart[c] .. tstart[c + 1]
    const double* xw          # wrapped targets, cell order
    const long* torder        # original index of each cell-ordered target
    const long* tvi           # own="smooth": own vesicle of each cell-ordered target (-1: none); NULL: own pairs summed
    bint do_sl
    bint do_dl


cdef inline double _gap(double x, double a, double w) noexcept nogil:
    """Distance from x to the interval [a, a + w] (0 inside)."""
    if x < a:
        return a - x
    if x > a + w:
        return x - a - w
    return 0.0


cdef void _cell_targets(const _Cells* b, long c, double* out) noexcept nogil:
    """out[3 torder[t] + a] += real-space sum of every target t of cell c.  The neighbour cells
    go by rows along axis 2 (consecutive cells of one image shift hold one range of sources);
    per group of targets with one own vesicle, the rows' pieces without that vesicle's runs are
    listed once; per target, the rows and cells farther than rc from it are dropped, the pieces
    clipped to the remaining cells and summed in place, the target moved by minus their shift."""
    cdef long cc[3]
    cdef long lo[3]
    cdef long hi[3]
    cdef long ec[3 * MAXW]                    # wrapped cell index of each neighbour position, per axis (2 SUB + 1 each)
    cdef double shc[3 * MAXW]                 # image shift, per axis
    cdef double bxc[3 * MAXW]                 # cell corner (unwrapped), per axis
    cdef long nc3[3]
    cdef double gp[3 * MAXW]                  # per target: gap to each neighbour position, per axis, squared
    cdef long j, k, i0, i1, i2, t, s, r, a, ca, cb, nr, np_, skip, cap = 0, first, last, t0, t1, base, s0, s1
    cdef long nrow, row
    cdef double o[3]
    cdef double x0, x1, x2, g01, gg
    cdef vf_range* rg
    cdef long* pc                       # pieces: 4 per piece (row, first and last position, unused)
    cdef long* ps                       # pieces' source ranges: s0, s1
    cdef long prow[MAXW * MAXW + 1]
    cc[0] = c // (b.n[1] * b.n[2])
    cc[1] = (c // b.n[2]) % b.n[1]
    cc[2] = c % b.n[2]
    for j in range(3):
        if b.periodic and b.mL[j] != 0.0:
            lo[j] = 0
            hi[j] = b.n[j] - 1
        elif b.periodic:
            lo[j] = cc[j] - SUB
            hi[j] = cc[j] + SUB
        else:
            lo[j] = cc[j] - SUB if cc[j] >= SUB else 0
            hi[j] = cc[j] + SUB if cc[j] + SUB < b.n[j] else b.n[j] - 1
        nc3[j] = hi[j] - lo[j] + 1
        for k in range(nc3[j]):
            ec[MAXW * j + k] = (lo[j] + k + b.n[j]) % b.n[j]
            shc[MAXW * j + k] = b.L[j] * ((lo[j] + k - ec[MAXW * j + k]) // b.n[j]) if b.periodic else 0.0
            bxc[MAXW * j + k] = b.lo[j] + (lo[j] + k) * b.side[j]
    nrow = nc3[0] * nc3[1]
    for i0 in range(nc3[0]):
        for i1 in range(nc3[1]):
            base = (ec[i0] * b.n[1] + ec[MAXW + i1]) * b.n[2]
            for i2 in range(nc3[2]):
                cap += b.crun[base + ec[2 * MAXW + i2] + 1] - b.crun[base + ec[2 * MAXW + i2]] + 1
    cap += 2 * nrow + 1
    rg = <vf_range*> malloc(cap * sizeof(vf_range))
    pc = <long*> malloc(cap * 3 * sizeof(long))
    ps = <long*> malloc(cap * 2 * sizeof(long))
    t0 = b.tstart[c]
    while t0 < b.tstart[c + 1]:
        # the targets t0 .. t1 - 1 share their own vesicle (skip; -1: none)
        skip = b.tvi[t0] if b.tvi != NULL else -1
        t1 = t0 + 1
        while t1 < b.tstart[c + 1] and (b.tvi[t1] if b.tvi != NULL else -1) == skip:
            t1 += 1
        # the group's pieces, row by row: per segment of consecutive cells (one shift), its
        # sources without the runs of vesicle skip
        np_ = 0
        for i0 in range(nc3[0]):
            for i1 in range(nc3[1]):
                row = i0 * nc3[1] + i1
                prow[row] = np_
                base = (ec[i0] * b.n[1] + ec[MAXW + i1]) * b.n[2]
                i2 = 0
                while i2 < nc3[2]:
                    ca = i2
                    while i2 + 1 < nc3[2] and ec[2 * MAXW + i2 + 1] == ec[2 * MAXW + i2] + 1:
                        i2 += 1
                    cb = i2
                    i2 += 1
                    a = b.cstart[base + ec[2 * MAXW + ca]]
                    if skip >= 0:
                        for r in range(b.crun[base + ec[2 * MAXW + ca]], b.crun[base + ec[2 * MAXW + cb] + 1]):
                            if b.rvi[r] == skip:
                                if b.rstart[r] > a:
                                    pc[3 * np_] = base
                                    pc[3 * np_ + 1] = ca
                                    pc[3 * np_ + 2] = cb
                                    ps[2 * np_] = a
                                    ps[2 * np_ + 1] = b.rstart[r]
                                    np_ += 1
                                a = b.rstart[r + 1]
                    s = b.cstart[base + ec[2 * MAXW + cb] + 1]
                    if s > a:
                        pc[3 * np_] = base
                        pc[3 * np_ + 1] = ca
                        pc[3 * np_ + 2] = cb
                        ps[2 * np_] = a
                        ps[2 * np_ + 1] = s
                        np_ += 1
        prow[nrow] = np_
        for t in range(t0, t1):
            x0 = b.xw[3 * t]
            x1 = b.xw[3 * t + 1]
            x2 = b.xw[3 * t + 2]
            for j in range(3):
                for k in range(nc3[j]):
                    gg = 0.0 if b.mL[j] != 0.0 else _gap(b.xw[3 * t + j], bxc[MAXW * j + k], b.side[j])
                    gp[MAXW * j + k] = gg * gg
            nr = 0
            for i0 in range(nc3[0]):
                for i1 in range(nc3[1]):
                    g01 = gp[i0] + gp[MAXW + i1]
                    if g01 > b.rc2_cull:
                        continue
                    # the row's cells within rc: first .. last (an interval: the distance is convex)
                    first = -1
                    last = -1
                    for i2 in range(nc3[2]):
                        if g01 + gp[2 * MAXW + i2] <= b.rc2_cull:
                            if first < 0:
                                first = i2
                            last = i2
                    if first < 0:
                        continue
                    row = i0 * nc3[1] + i1
                    for k in range(prow[row], prow[row + 1]):
                        ca = pc[3 * k + 1] if pc[3 * k + 1] > first else first
                        cb = pc[3 * k + 2] if pc[3 * k + 2] < last else last
                        if ca > cb:
                            continue
                        s0 = b.cstart[pc[3 * k] + ec[2 * MAXW + ca]]
                        s1 = b.cstart[pc[3 * k] + ec[2 * MAXW + cb] + 1]
                        s0 = ps[2 * k] if ps[2 * k] > s0 else s0
                        s1 = ps[2 * k + 1] if ps[2 * k + 1] < s1 else s1
                        if s0 >= s1:
                            continue
                        rg[nr].s0 = s0
                        rg[nr].s1 = s1
                        rg[nr].x[0] = x0 - shc[i0]
                        rg[nr].x[1] = x1 - shc[MAXW + i1]
                        rg[nr].x[2] = x2 - shc[2 * MAXW + pc[3 * k + 1]]
                        nr += 1
            o[0] = 0.0
            o[1] = 0.0
            o[2] = 0.0
            if nr > 0:
                vf_ewald_real(b.ys, b.dens, b.ld, rg, nr, b.xi, b.rc2, b.mL, b.iL, b.mi_any, b.do_sl, b.do_dl, o)
            s = b.torder[t]
            out[3 * s] += o[0]
            out[3 * s + 1] += o[1]
            out[3 * s + 2] += o[2]
        t0 = t1
    free(rg)
    free(pc)
    free(ps)


class RealSpace:
    """The real-space sum (module docstring) for a fixed geometry: the cell lists and sorted
    points are built once here, :meth:`apply` takes the densities.

    src (S, 3) SORTED by vesicle id, vesicle v's sources ``src_off[v] .. src_off[v+1]``,
    src_id (S,); trg (T, 3), trg_id (T,), trg_vi (T,): index v of the target's own vesicle or
    -1; lo, length (3,): the box (periodic: the period cell; free: a box holding every point);
    skip_own: leave every target's own vesicle out, no own subtraction (module docstring).
    """

    def __init__(self, src, src_id, src_off, trg, trg_id, trg_vi, double xi, double rc, lo, length,
                 bint periodic, bint skip_own=False):
        src_np = np.ascontiguousarray(src, dtype=np.float64).reshape(-1, 3)
        trg_np = np.ascontiguousarray(trg, dtype=np.float64).reshape(-1, 3)
        ns, nt = src_np.shape[0], trg_np.shape[0]
        if not (rc > 0.0 and xi > 0.0):
            raise ValueError(f"rc and xi must be positive, got {rc}, {xi}")
        lo_np = np.asarray(lo, dtype=np.float64).reshape(3)
        len_np = np.asarray(length, dtype=np.float64).reshape(3)
        ncell = np.maximum(1, np.floor(len_np / (rc / SUB))).astype(np.int64)
        while np.prod(ncell) > 4 * ns + 64:
            j = int(np.argmax(ncell))
            ncell[j] = max(1, ncell[j] // 2)
        side = np.where(len_np > 0, len_np / ncell, 1.0)
        if periodic:
            if np.any(rc >= 0.5 * len_np):
                raise ValueError(f"periodic real-space cutoff rc = {rc} must be below half the period {len_np}")
            sw = lo_np + np.mod(src_np - lo_np, len_np)
            tw = lo_np + np.mod(trg_np - lo_np, len_np)
        else:
            sw, tw = src_np, trg_np
        ncells = int(np.prod(ncell))

        def key(pw):
            c = np.clip(np.floor((pw - lo_np) / side).astype(np.int64), 0, ncell - 1)
            return (c[:, 0] * ncell[1] + c[:, 1]) * ncell[2] + c[:, 2]

        skey, tkey = key(sw), key(tw)
        vi = np.asarray(trg_vi, dtype=np.int64).reshape(-1)
        nv = len(src_off) - 1
        src_vi = np.repeat(np.arange(nv, dtype=np.int64), np.diff(np.asarray(src_off, dtype=np.int64)))
        # sources by cell, within a cell by vesicle (stable: each vesicle's run keeps its surface order)
        sorder = np.lexsort((src_vi, skey))
        torder = np.lexsort((vi, tkey)) if skip_own else np.argsort(tkey, kind="stable")
        self.skip_own = bool(skip_own)
        self.tvi = np.ascontiguousarray(vi[torder], dtype=np.int64) if skip_own else None
        self.ncell, self.length, self.periodic, self.xi, self.rc = ncell, len_np, bool(periodic), xi, rc
        self.lo, self.side = lo_np, side
        self.ns, self.nt = ns, nt
        self.sorder = sorder
        self.cstart = np.zeros(ncells + 1, dtype=np.int64)
        self.cstart[1:] = np.cumsum(np.bincount(skey, minlength=ncells))
        self.tstart = np.zeros(ncells + 1, dtype=np.int64)
        self.tstart[1:] = np.cumsum(np.bincount(tkey, minlength=ncells))
        self.tcells = np.flatnonzero(np.diff(self.tstart)).astype(np.int64)   # cells holding targets
        # runs: the sources of one vesicle in one cell (cell c's runs crun[c] .. crun[c + 1])
        ks, vs = skey[sorder], src_vi[sorder]
        heads = np.flatnonzero(np.r_[True, (ks[1:] != ks[:-1]) | (vs[1:] != vs[:-1])]) if ns else np.zeros(0, np.int64)
        self.rstart = np.ascontiguousarray(np.r_[heads, ns], dtype=np.int64)
        self.rvi = np.ascontiguousarray(vs[heads], dtype=np.int64)
        self.crun = np.ascontiguousarray(np.searchsorted(heads, self.cstart), dtype=np.int64)
        # source positions in place, structure of arrays, VF_BLOCK padding rows (read, masked)
        self.ld = ns + VF_BLOCK
        self.ys = np.zeros((3, self.ld))
        self.ys[:, :ns] = sw[sorder].T
        self.xw = np.ascontiguousarray(tw[torder])
        # the targets with an own vesicle grouped by it (own-vesicle sums): original indices
        # oidx, given positions xo, vesicle v's at ostart[v] .. ostart[v + 1]
        self.oidx = np.ascontiguousarray(np.flatnonzero(vi >= 0)[np.argsort(vi[vi >= 0], kind="stable")], dtype=np.int64)
        self.xo = np.ascontiguousarray(trg_np[self.oidx]).reshape(-1, 3)
        self.ostart = np.zeros(nv + 1, dtype=np.int64)
        self.ostart[1:] = np.cumsum(np.bincount(vi[vi >= 0], minlength=nv))
        self.torder = np.ascontiguousarray(torder, dtype=np.int64)
        self.src = src_np
        self.src_off = np.ascontiguousarray(src_off, dtype=np.int64)

    def apply(self, f, nw, g, out):
        """out (T, 3) += the real-space sum, 1/(8 pi) included; f (S, 3) or (0, 3): single-layer
        density times weight; nw, g (S, 3) or (0, 3): double layer; id-sorted as src."""
        _apply_cells(self, np.ascontiguousarray(f, dtype=np.float64), np.ascontiguousarray(nw, dtype=np.float64),
                     np.ascontiguousarray(g, dtype=np.float64), out)


cdef void _gather_columns(const double[:, ::1] a, const long[::1] order, double[:, ::1] out, Py_ssize_t col) noexcept:
    """out[col + c, k] = a[order[k], c] (c < 3): rows in cell order into columns (OpenMP)."""
    cdef Py_ssize_t k, j, n = order.shape[0]
    with nogil:
        for k in prange(n, schedule="static"):
            j = order[k]
            out[col, k] = a[j, 0]
            out[col + 1, k] = a[j, 1]
            out[col + 2, k] = a[j, 2]


def _apply_cells(rs, const double[:, ::1] f, const double[:, ::1] nw, const double[:, ::1] g, double[:, ::1] out):
    cdef Py_ssize_t ns = rs.ns, nt = rs.nt
    cdef bint do_sl = f.shape[0] > 0, do_dl = g.shape[0] > 0
    if do_sl and f.shape[0] != ns:
        raise ValueError(f"f has {f.shape[0]} rows, src has {ns}")
    if do_dl and (g.shape[0] != ns or nw.shape[0] != ns):
        raise ValueError(f"nw, g have {nw.shape[0]}, {g.shape[0]} rows, src has {ns}")
    if out.shape[0] != nt:
        raise ValueError(f"out has {out.shape[0]} rows, trg has {nt}")
    if nt == 0 or ns == 0 or not (do_sl or do_dl):
        return
    # the densities in cell order, columns of ld rows (the padding rows 0)
    cdef Py_ssize_t ld = rs.ld
    dens_np = np.empty((3 * (do_sl + 2 * do_dl), ld))
    dens_np[:, ns:] = 0.0
    cdef double[:, ::1] dens = dens_np
    cdef long[::1] sorder = rs.sorder
    cdef Py_ssize_t col = 0
    if do_sl:
        _gather_columns(f, sorder, dens, col)
        col += 3
    if do_dl:
        _gather_columns(nw, sorder, dens, col)
        _gather_columns(g, sorder, dens, col + 3)
    cdef double[:, ::1] ys = rs.ys, xw = rs.xw, xo = rs.xo, src = rs.src
    cdef long[::1] cstart = rs.cstart, tstart = rs.tstart, crun = rs.crun, rstart = rs.rstart, rvi = rs.rvi
    cdef long[::1] torder = rs.torder, src_off = rs.src_off, tcells = rs.tcells, ostart = rs.ostart
    cdef _Cells b
    cdef int j
    b.mi_any = False
    for j in range(3):
        b.n[j] = rs.ncell[j]
        b.L[j] = rs.length[j]
        b.lo[j] = rs.lo[j]
        b.side[j] = rs.side[j]
        b.mL[j] = rs.length[j] if (rs.periodic and rs.ncell[j] < 2 * SUB + 1) else 0.0
        b.iL[j] = 1.0 / rs.length[j] if b.mL[j] != 0.0 else 0.0
        b.mi_any = b.mi_any or b.mL[j] != 0.0
    b.periodic = rs.periodic
    b.rc2 = rs.rc * rs.rc
    b.rc2_cull = b.rc2 * (1.0 + 1e-9)
    b.xi = rs.xi
    b.ld = ld
    b.ys = &ys[0, 0]
    b.dens = &dens[0, 0]
    b.cstart = &cstart[0]
    b.crun = &crun[0]
    b.rstart = &rstart[0]
    b.rvi = &rvi[0] if rvi.shape[0] > 0 else NULL
    b.tstart = &tstart[0]
    b.xw = &xw[0, 0]
    b.torder = &torder[0]
    b.do_sl = do_sl
    b.do_dl = do_dl
    cdef long[::1] tvi
    b.tvi = NULL
    if rs.skip_own:
        tvi = rs.tvi
        b.tvi = &tvi[0]
    cdef double* po = &out[0, 0]
    cdef const long* pc = &tcells[0]
    cdef Py_ssize_t k, nc = tcells.shape[0]
    with nogil:
        for k in prange(nc, schedule="dynamic", chunksize=8):
            _cell_targets(&b, pc[k], po)
    if rs.skip_own:
        return
    # minus each vesicle's full kernel at its own targets (r = 0 skipped), the targets of a
    # vesicle 4 at a time against its sources (pairsum.h)
    own = np.zeros((xo.shape[0], 3))
    cdef double[:, ::1] ow = own
    cdef Py_ssize_t v, nv = ostart.shape[0] - 1
    cdef const double* pf = &f[0, 0] if do_sl else NULL
    cdef const double* pn = &nw[0, 0] if do_dl else NULL
    cdef const double* pg = &g[0, 0] if do_dl else NULL
    if xo.shape[0] > 0:
        with nogil:
            for v in prange(nv, schedule="dynamic"):
                if ostart[v + 1] > ostart[v]:
                    if do_sl:
                        vf_stokeslet_targets(&src[0, 0], pf, src_off[v], src_off[v + 1], &xo[ostart[v], 0],
                                             ostart[v + 1] - ostart[v], &ow[ostart[v], 0])
                    if do_dl:
                        vf_stresslet_targets(&src[0, 0], pn, pg, src_off[v], src_off[v + 1], &xo[ostart[v], 0],
                                             ostart[v + 1] - ostart[v], &ow[ostart[v], 0])
        _scatter_sub(out, rs.oidx, own)


def _scatter_sub(double[:, ::1] out, const long[::1] idx, const double[:, ::1] val):
    """out[idx[k]] -= val[k] (distinct idx)."""
    cdef Py_ssize_t k
    for k in range(idx.shape[0]):
        out[idx[k], 0] -= val[k, 0]
        out[idx[k], 1] -= val[k, 1]
        out[idx[k], 2] -= val[k, 2]

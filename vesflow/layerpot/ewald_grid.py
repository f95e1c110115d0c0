"""The Fourier part of the spectral Ewald sum on a grid split over the ranks
(docs/explanation/parallel.md, "Distributed Ewald grid"; the sum itself: vesflow.layerpot.ewald's
module docstring, ``u^F``).

The same sum as the replicated path (type-1 NUFFT, Psi multiplier, type-2 NUFFT) built from its
parts, with the fine grid cut into z-slabs, one per rank:

- **spreading** (Dutt and Rokhlin 1993; the "exponential of semicircle" kernel ``psi`` of
  Barnett, Magland and af Klinteberg 2019, width ``w`` and ``beta`` from the tolerance by
  :func:`es_kernel`): each real source component ``c_s`` is spread onto the fine grid
  (``n_a >= sigma K_a`` cells of ``h_a = P_a / n_a``, sigma = :func:`upsample_for`) as
  ``G_j = sum_s c_s psi(z_x) psi(z_y) psi(z_z)``, ``z = (j - u_s) / (w / 2)``; a rank spreads its own sources into a box of the
  periodic grid that covers its sources' and targets' stencils (:func:`cover`: per axis the
  shortest periodic arc; the sources of a rank are spatially sorted, so the box is compact)
  and sends each z-plane of the box to the rank owning it, which adds it into its slab
  (the ghost contributions);
- **the FFT** of the real slabs: real-to-complex along x, along y, an Alltoallv transpose of
  the kept modes only (``|m_a| < K_a / 2``: a fraction ``~1 / (2 sigma^2)`` of the fine
  grid) from z-slabs to y-slabs of the modes, along z; then
  ``F(k) = G^(m) / (psi^_x psi^_y psi^_z)`` (``psi^(theta) = int psi(2 t / w) cos(theta t) dt``,
  ``theta = 2 pi m / n``: :func:`kernel_ft`);
- **the multiplier** ``U = (1/V) Psi [(k^2 F - k (k.F)) + i (k^2 (2 S k + k tr S) - 2 k (k.S k))]``
  on the rank's modes (the modes with an index -K/2 and k = 0 are 0, as in the replicated path);
- **the inverse**: ``U / (psi^_x psi^_y psi^_z)`` through the same steps backwards to real
  velocity slabs, the planes of each rank's box sent back from their owners, and
  ``u_t = sum_j g_j psi psi psi`` at the rank's targets (vesflow._kernels.spread).

Periodic and free space alike (free space: the windowed Psi on the padded period; the points
then fill part of the grid and the boxes are smaller).  One process is the one-rank case (no
communication; the box is the one slab when it covers the whole grid, else added into it).
"""
from __future__ import annotations

import math

import numpy as np
import scipy.fft

from vesflow._kernels import spread as _spread

from .ewald_fourier import kernel_psi

GRID_MODES = ("replicated", "distributed")
# fine grid per axis over the mode count (the kernel width and beta for it: es_kernel): 1.5 down
# to eps 1e-10 (w = 9, 12 for the kernel's eps 1e-7, 1e-9; 0.42x the grid of 2.0 for ~1.7x the
# stencil), 2.0 below (w = 16 at 1.5 reaches 1e-12 only at the limit; at 2.0 w = 12, 14 for 1e-11,
# 1e-13); measured errors: tests/layerpot/test_ewald_grid.py
UPSAMPLE_COARSE, UPSAMPLE_FINE, UPSAMPLE_SWITCH = 1.5, 2.0, 1e-10
MAX_WIDTH = 16
# the kernel is chosen for EPS_FACTOR times the NUFFT accuracy the Ewald parameters ask for: the
# ES rule at eps gives 0.4-0.9 eps relative to the largest velocity (tests/layerpot/test_ewald_grid.py's
# scene), ducc0's NUFFT at eps 0.01-0.02 eps; at eps / 10 the Fourier part's error is 0.04-0.13 eps
# (the same scene, 1e-6 .. 1e-12), within the margin of vesflow.layerpot.ewald.NUFFT_EPS_FACTOR
EPS_FACTOR = 0.1


def upsample_for(eps):
    """Fine grid over the modes per axis for the accuracy eps (UPSAMPLE_*)."""
    return UPSAMPLE_COARSE if eps >= UPSAMPLE_SWITCH else UPSAMPLE_FINE


def es_kernel(eps, upsample):
    """``(w, beta)`` of the ES kernel for a relative accuracy ``eps`` on a grid ``upsample``
    times the modes: finufft's rule (Barnett et al. 2019, section 4: ``w = ceil(log10(1/eps)) + 1``,
    ``beta = 2.30 w`` at upsampling 2; ``w = ceil(ln(1/eps) / (pi sqrt(1 - 1/sigma)))``,
    ``beta = 0.97 pi (1 - 1/(2 sigma)) w`` otherwise), w in 2 .. 16."""
    if upsample == 2.0:
        w = math.ceil(-math.log10(eps / 10.0))
    else:
        w = math.ceil(-math.log(eps) / (math.pi * math.sqrt(1.0 - 1.0 / upsample)))
    w = min(MAX_WIDTH, max(2, w))
    if upsample == 2.0:
        bw = {2: 2.20, 3: 2.26, 4: 2.38}.get(w, 2.30)
    else:
        bw = 0.97 * math.pi * (1.0 - 0.5 / upsample)
    return w, bw * w


def kernel_ft(w, beta, theta):
    """``psi^(theta) = int_{-w/2}^{w/2} psi(2 t / w) cos(theta t) dt`` (grid units), by
    Gauss-Legendre quadrature (the kernel is even and smooth inside its support)."""
    x, wq = np.polynomial.legendre.leggauss(max(64, 4 * w + 40))
    t = 0.5 * w * x
    psi = np.exp(beta * (np.sqrt(1.0 - x * x) - 1.0))
    th = np.asarray(theta, dtype=np.float64)
    return (np.cos(np.multiply.outer(th, t)) @ (psi * wq)) * (0.5 * w)


def fine_size(modes, upsample):
    """Fine cells per axis: the next fast FFT length >= upsample * modes."""
    return scipy.fft.next_fast_len(int(math.ceil(upsample * modes)), real=True)


def cover(u, n, w):
    """``(start, length)`` of the shortest periodic arc of the n cells of one axis that holds
    every cell the stencils of the points at grid coordinates ``u`` touch (``length = n``:
    the whole axis; 0 without points)."""
    if u.size == 0:
        return 0, 0
    i0 = np.unique(np.mod(np.ceil(u - 0.5 * w).astype(np.int64), n))
    occ = np.zeros(n, dtype=bool)
    occ[np.mod(i0[:, None] + np.arange(w), n)] = True
    on = np.flatnonzero(occ)
    if on.size == n:
        return 0, n
    gaps = np.diff(np.concatenate([on, [on[0] + n]]))      # gaps[i]: from on[i] to the next occupied cell
    i = int(np.argmax(gaps))
    start = int(on[(i + 1) % on.size])
    return start, n - int(gaps[i] - 1)


def _splits(n, size):
    """Offsets (size + 1,) of n items cut into size near-equal contiguous blocks."""
    return np.array([r * n // size for r in range(size + 1)], dtype=np.int64)


def slab_bytes(m, n, blen, zl, yl, K, size=2):
    """Bytes of one rank's grid arrays at the peak of an evaluation with m real source
    components on the fine grid n (x, y, z), a box of blen cells, zl z-planes of the slab, yl
    y-modes of the mode slab, K modes per axis, size ranks: the box and the slab of one
    component (real), and the largest of: one component's x, y transforms beside the
    transpose's send buffer (all m components' kept modes), the send and receive buffers, the
    received modes with the z-transforms (one component's grid and its transform), the
    multiplier's input and output, the inverse's y, x transforms of one component beside the
    velocity modes (complex); the multiplier (real) besides."""
    nx, ny, nz = n
    kx, ky, kz = K[0] // 2, K[1] - 1, K[2] - 1
    out = {"box": 8 * int(np.prod(blen)), "slab": 8 * zl * ny * nx}
    send, recv, full, F = (16 * m * zl * ky * kx, 16 * m * nz * yl * kx, 16 * nz * yl * kx, 16 * m * kz * yl * kx)
    if size == 1:
        recv = send                               # the send buffer itself
        send = 0
    half, xy = 16 * zl * ny * (nx // 2 + 1), 16 * zl * ny * kx
    back = 16 * 3 * zl * ky * kx                  # the three velocity components' modes, z-slab layout
    out["transforms"] = max(max(send, recv) + half + xy + 16 * zl * ky * kx,  # forward x, y of one component
                            send + recv, recv + 2 * full + F,                # transpose, z (one component)
                            F + 16 * 3 * kz * yl * kx,                       # the multiplier
                            back + half + xy + 8 * zl * ny * nx)             # inverse y, x of one component
    out["multiplier"] = 8 * kz * yl * kx
    out["total"] = sum(out.values())
    return out


class _Comm:
    """The few collectives used here, on an mpi4py communicator or None (one process)."""

    def __init__(self, comm):
        self.comm = comm
        self.rank, self.size = (0, 1) if comm is None else (comm.Get_rank(), comm.Get_size())

    def allgather(self, x):
        return [x] if self.comm is None else self.comm.allgather(x)

    def alltoallv(self, send, scounts, rcounts):
        """float64 Alltoallv (counts in doubles, rank order, contiguous blocks); returns the
        received buffer (one process: ``send`` itself)."""
        if self.comm is None:
            return send
        from mpi4py import MPI
        scounts = np.asarray(scounts, dtype=np.int64)
        rcounts = np.asarray(rcounts, dtype=np.int64)
        recv = np.empty(int(rcounts.sum()))
        sd = np.concatenate([[0], np.cumsum(scounts)[:-1]]).astype(np.int64)
        rd = np.concatenate([[0], np.cumsum(rcounts)[:-1]]).astype(np.int64)
        self.comm.Alltoallv([send, scounts, sd, MPI.DOUBLE], [recv, rcounts, rd, MPI.DOUBLE])
        return recv


class DistributedFourier:
    """The Fourier part ``u^F`` (module docstring) at this rank's targets ``trg01`` (T, 3) from
    its sources ``src01`` (S, 3), both in [0, 2 pi) per axis as the NUFFT's points
    (vesflow.layerpot.ewald.EwaldSum), for the Ewald parameters ``p``; ``comm`` an mpi4py
    communicator over which the grid is split (None: one process); ``eps`` the accuracy of the
    spreading and interpolation (default EPS_FACTOR p.nufft_eps)."""

    def __init__(self, p, src01, trg01, comm=None, threads=1, eps=None, upsample=None, psi=None):
        self.p, self.threads = p, max(1, int(threads))
        self._psi_full = psi
        self.c = c = _Comm(comm)
        self.eps = max(p.nufft_eps * EPS_FACTOR, 1e-14) if eps is None else float(eps)
        self.upsample = upsample_for(self.eps) if upsample is None else float(upsample)
        self.w, self.beta = es_kernel(self.eps, self.upsample)
        K = [int(k) for k in p.modes]                            # x, y, z
        self.K = K
        self.n = n = [fine_size(k, self.upsample) for k in K]        # fine cells, x, y, z
        if min(n) < 2 * self.w:
            n = self.n = [max(v, scipy.fft.next_fast_len(2 * self.w, real=True)) for v in n]
        nx, ny, nz = n
        # points in grid units (x, y, z) in [0, n)
        scale = np.asarray(n, dtype=np.float64) / (2.0 * math.pi)

        def grid_units(a):
            u = np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1, 3) * scale)
            for ax in range(3):
                col = u[:, ax]
                col[col >= n[ax]] -= n[ax]
                col[col < 0] += n[ax]
            return u
        self.us, self.ut = grid_units(src01), grid_units(trg01)
        both = np.concatenate([self.us, self.ut])
        arcs = [cover(both[:, ax], n[ax], self.w) for ax in range(3)]
        self.start = [a[0] for a in arcs]                       # x, y, z
        self.blen = [a[1] for a in arcs]
        # every rank's box; z-slabs of the fine grid; y-slabs of the kept modes
        self.boxes = c.allgather((tuple(self.start), tuple(self.blen)))
        self.zoff = _splits(nz, c.size)
        self.my = np.arange(-(K[1] // 2) + 1, K[1] // 2)             # kept y modes, ascending
        self.mz = np.arange(-(K[2] // 2) + 1, K[2] // 2)
        self.mx = np.arange(0, K[0] // 2)                            # x: the real-to-complex half
        self.yoff = _splits(self.my.size, c.size)
        r = c.rank
        self.z0, self.z1 = int(self.zoff[r]), int(self.zoff[r + 1])
        self.y0, self.y1 = int(self.yoff[r]), int(self.yoff[r + 1])
        self._plan_exchange()
        self._multiplier()
        self.bytes_sent = 0                  # counted over the evaluations (not to this rank)
        self.evaluations = 0

    # ------------------------------------------------------------------ set-up
    def _plan_exchange(self):
        """Which planes of which box go to which slab: for every (sender, owner) pair the box
        planes j whose global plane (start_z + j) mod n_z the owner holds."""
        nz = self.n[2]
        self._planes = {}                    # (sender, owner) -> (box planes j, slab planes - z0 of owner)
        for s, (st, ln) in enumerate(self.boxes):
            g = np.mod(st[2] + np.arange(ln[2]), nz)
            for o in range(self.c.size):
                z0, z1 = self.zoff[o], self.zoff[o + 1]
                j = np.flatnonzero((g >= z0) & (g < z1))
                self._planes[(s, o)] = (j, g[j] - z0)

    def _multiplier(self):
        """The real factor ``Psi (1/V) / (psi^_x psi^_y psi^_z)^2`` on this rank's modes
        (kept z, local y, kept x >= 0), and the wave numbers."""
        p, n, K = self.p, self.n, self.K
        psi = kernel_psi(p, self.threads) if self._psi_full is None else self._psi_full   # [|mx|, |my|, |mz|]
        self._psi_full = None
        mx, my, mz = self.mx, self.my[self.y0:self.y1], self.mz
        dx = kernel_ft(self.w, self.beta, 2 * math.pi * mx / n[0])
        dy = kernel_ft(self.w, self.beta, 2 * math.pi * my / n[1])
        dz = kernel_ft(self.w, self.beta, 2 * math.pi * mz / n[2])
        ps = psi[np.ix_(np.abs(mx), np.abs(my), np.abs(mz))].transpose(2, 1, 0)       # (z, y, x)
        ps = ps / (dz[:, None, None] * dy[None, :, None] * dx[None, None, :]) ** 2
        ps /= float(np.prod(p.period))
        self._ps = np.ascontiguousarray(ps)
        self._k = [2 * math.pi / p.period[0] * mx, 2 * math.pi / p.period[1] * my, 2 * math.pi / p.period[2] * mz]

    # ------------------------------------------------------------------ sizes
    def grid_bytes(self, m):
        """Bytes of this rank's grid arrays for m source components (:func:`slab_bytes`)."""
        b = slab_bytes(m, self.n, self.blen, self.z1 - self.z0, self.y1 - self.y0, self.K, self.c.size)
        if self.c.size == 1 and list(self.blen) == list(self.n) and not any(self.start):
            b["total"] -= b["slab"]                   # the box is the slab
            b["slab"] = 0
        return b

    # ------------------------------------------------------------------ steps
    def _box_to_slabs(self, box, slab):
        """Send each plane of this rank's box to its owner; add the received planes into slab
        (m, z1 - z0, ny, nx)."""
        c, r, m = self.c, self.c.rank, box.shape[0]
        ny, nx = self.n[1], self.n[0]
        send = [np.ascontiguousarray(box[:, self._planes[(r, o)][0]]).reshape(-1) for o in range(c.size)]
        scounts = [a.size for a in send]
        rshapes = []
        for s in range(c.size):
            st, ln = self.boxes[s]
            rshapes.append((m, self._planes[(s, r)][0].size, ln[1], ln[0]))
        rcounts = [int(np.prod(sh)) for sh in rshapes]
        recv = c.alltoallv(np.concatenate(send), scounts, rcounts)
        self.bytes_sent += 8 * (sum(scounts) - scounts[r])
        slab[...] = 0.0
        at = 0
        for s in range(c.size):
            cnt = rcounts[s]
            if cnt:
                st, ln = self.boxes[s]
                zl = self._planes[(s, r)][1]
                gy = np.mod(st[1] + np.arange(ln[1]), ny)
                gx = np.mod(st[0] + np.arange(ln[0]), nx)
                slab[np.ix_(np.arange(m), zl, gy, gx)] += recv[at:at + cnt].reshape(rshapes[s])
            at += cnt

    def _slabs_to_box(self, slab, box):
        """The reverse of _box_to_slabs: fill this rank's box from the owners' slabs."""
        c, r, m = self.c, self.c.rank, slab.shape[0]
        ny, nx = self.n[1], self.n[0]
        send = []
        for s in range(c.size):
            st, ln = self.boxes[s]
            zl = self._planes[(s, r)][1]
            if zl.size == 0:
                send.append(np.empty(0))
                continue
            gy = np.mod(st[1] + np.arange(ln[1]), ny)
            gx = np.mod(st[0] + np.arange(ln[0]), nx)
            send.append(slab[np.ix_(np.arange(m), zl, gy, gx)].reshape(-1))
        scounts = [a.size for a in send]
        rcounts = [m * self._planes[(r, o)][0].size * self.blen[1] * self.blen[0] for o in range(c.size)]
        recv = c.alltoallv(np.concatenate(send), scounts, rcounts)
        self.bytes_sent += 8 * (sum(scounts) - scounts[r])
        at = 0
        for o in range(c.size):
            j = self._planes[(r, o)][0]
            if j.size:
                box[:, j] = recv[at:at + rcounts[o]].reshape(m, j.size, self.blen[1], self.blen[0])
            at += rcounts[o]

    def _segments(self, buf, q, zcounts, ycounts):
        """Views of the complex buffer ``buf`` as one (q, zcounts[r], ycounts[r], kept x) block per
        rank r (the blocks of a transpose, rank order)."""
        kx, out, at = self.mx.size, [], 0
        for zc, yc in zip(zcounts, ycounts):
            out.append(buf[at:at + q * zc * yc * kx].reshape(q, zc, yc, kx))
            at += q * zc * yc * kx
        return out

    def _forward(self, comps, box, slab, whole):
        """Spread each source component, its planes to the owners' slabs, its kept modes along
        x and y (real-to-complex x, complex y; one component's slab at a time), the transpose to
        y-slabs of the modes, the FFT along z: this rank's modes (m, kept z, local y, kept x),
        unnormalized ``sum_j G_j e^{-2 pi i m.j / n}``."""
        c, m = self.c, comps.shape[0]
        nx, ny, nz = self.n
        zl, yl, kx = self.z1 - self.z0, self.y1 - self.y0, self.mx.size
        ky = np.mod(self.my, ny)
        ycount = np.diff(self.yoff)
        zcount = np.diff(self.zoff)
        send = np.empty(m * zl * self.my.size * kx, dtype=np.complex128)
        blocks = self._segments(send, m, [zl] * c.size, ycount)
        for a in range(m):
            box.fill(0.0)
            _spread.spread(self.us, np.ascontiguousarray(comps[a:a + 1]), box, self.n, self.start, self.w, self.beta)
            if not whole:
                self._box_to_slabs(box, slab)
            h = scipy.fft.rfft(slab[0], axis=-1, workers=self.threads)[..., :kx]
            h = scipy.fft.fft(h, axis=1, workers=self.threads, overwrite_x=True)[:, ky]
            for o in range(c.size):
                blocks[o][a] = h[:, self.yoff[o]:self.yoff[o + 1]]
            del h
        recv = c.alltoallv(send.view(np.float64), [2 * b.size for b in blocks],
                           2 * m * zcount * yl * kx).view(np.complex128)
        self.bytes_sent += 16 * (send.size - blocks[c.rank].size)
        del send, blocks
        rblocks = self._segments(recv, m, zcount, [yl] * c.size)
        F = np.empty((m, self.mz.size, yl, kx), dtype=np.complex128)
        kz = np.mod(self.mz, nz)
        for a in range(m):
            full = np.empty((nz, yl, kx), dtype=np.complex128)
            for s_ in range(c.size):
                full[self.zoff[s_]:self.zoff[s_ + 1]] = rblocks[s_][a]
            F[a] = scipy.fft.fft(full, axis=0, workers=self.threads, overwrite_x=True)[kz]
            del full
        return F

    def _inverse(self, U, box, slab, whole):
        """This rank's modes U (3, kept z, local y, kept x) -> real z-slabs of
        ``sum_m U_m e^{2 pi i m.j / n}``, one component at a time, its planes back to the boxes
        and interpolated at this rank's targets: (3, T)."""
        c = self.c
        nx, ny, nz = self.n
        kx, yl, zl = self.mx.size, self.y1 - self.y0, self.z1 - self.z0
        q = U.shape[0]
        ycount = np.diff(self.yoff)
        zcount = np.diff(self.zoff)
        send = np.empty(q * nz * yl * kx, dtype=np.complex128)
        blocks = self._segments(send, q, zcount, [yl] * c.size)
        kz = np.mod(self.mz, nz)
        for a in range(q):
            full = np.zeros((nz, yl, kx), dtype=np.complex128)
            full[kz] = U[a]
            full = scipy.fft.ifft(full, axis=0, norm="forward", workers=self.threads, overwrite_x=True)
            for o in range(c.size):
                blocks[o][a] = full[self.zoff[o]:self.zoff[o + 1]]
            del full
        recv = c.alltoallv(send.view(np.float64), [2 * b.size for b in blocks],
                           2 * q * zl * ycount * kx).view(np.complex128)
        self.bytes_sent += 16 * (send.size - blocks[c.rank].size)
        del send, blocks
        rblocks = self._segments(recv, q, [zl] * c.size, ycount)
        ky = np.mod(self.my, ny)
        out = np.empty((q, self.ut.shape[0]))
        for a in range(q):
            h = np.zeros((zl, ny, nx // 2 + 1), dtype=np.complex128)
            for s_ in range(c.size):
                h[:, ky[self.yoff[s_]:self.yoff[s_ + 1]], :kx] = rblocks[s_][a]
            h[:, :, :kx] = scipy.fft.ifft(h[:, :, :kx], axis=1, norm="forward", workers=self.threads)
            slab[0] = scipy.fft.irfft(h, n=nx, axis=-1, norm="forward", workers=self.threads, overwrite_x=True)
            del h
            if not whole:
                self._slabs_to_box(slab, box)
            _spread.interpolate(self.ut, box, out[a:a + 1], self.n, self.start, self.w, self.beta, self.threads)
        return out

    def _apply_multiplier(self, F, single, double):
        """U (3, ...) from the modes F of the source components (f_0..2 if ``single``, then
        S_00, S_11, S_22, S_01, S_02, S_12 if ``double``): module docstring.  In chunks of
        z-planes (the temporaries stay small)."""
        kx, ky, kz = self._k
        a = kx[None, None, :]
        b = ky[None, :, None]
        U = np.zeros((3,) + F.shape[1:], dtype=np.complex128)
        step = max(1, (1 << 16) // max(1, F.shape[2] * F.shape[3]))
        for i0 in range(0, F.shape[1], step):
            sl = slice(i0, i0 + step)
            f, u = F[:, sl], U[:, sl]
            cz = kz[sl, None, None]
            kk = a * a + b * b + cz * cz
            o = 0
            if single:
                kf = a * f[0] + b * f[1] + cz * f[2]
                u[0] = kk * f[0] - a * kf
                u[1] = kk * f[1] - b * kf
                u[2] = kk * f[2] - cz * kf
                o = 3
            if double:
                s00, s11, s22, s01, s02, s12 = (f[o + i] for i in range(6))
                q0 = s00 * a + s01 * b + s02 * cz
                q1 = s01 * a + s11 * b + s12 * cz
                q2 = s02 * a + s12 * b + s22 * cz
                tr = s00 + s11 + s22
                ksk = a * q0 + b * q1 + cz * q2
                u[0] += 1j * (kk * (2.0 * q0 + a * tr) - 2.0 * a * ksk)
                u[1] += 1j * (kk * (2.0 * q1 + b * tr) - 2.0 * b * ksk)
                u[2] += 1j * (kk * (2.0 * q2 + cz * tr) - 2.0 * cz * ksk)
            u *= self._ps[sl]
        return U

    def apply(self, comps, single, double):
        """``u^F`` (T, 3) at this rank's targets from the real source components ``comps``
        (m, S) of this rank's sources (single layer f w: 3 rows; double layer: the 6 of sym6;
        both: 9).  One component's box and slab at a time (module docstring)."""
        comps = np.ascontiguousarray(comps, dtype=np.float64)
        nx, ny, nz = self.n
        box = np.empty((1, self.blen[2], self.blen[1], self.blen[0]))
        # one rank whose box is the whole grid from cell 0: the box is the slab
        whole = self.c.size == 1 and list(self.blen) == list(self.n) and not any(self.start)
        slab = box if whole else np.empty((1, self.z1 - self.z0, ny, nx))
        F = self._forward(comps, box, slab, whole)
        U = self._apply_multiplier(F, single, double)
        del F
        out = self._inverse(U, box, slab, whole)
        self.evaluations += 1
        return np.ascontiguousarray(out.T)

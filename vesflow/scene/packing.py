"""Overlap checks of the initial vesicles and random packings (scene lattices).

Candidates are pruned by bounding spheres with a k-d tree (periodic images included);
quadric pairs are decided exactly by the Perram-Wertheim contact function, biconcave ones
through their enclosing spheroid, then by dense sampling and inside tests (both ways)."""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..errors import SceneError
from .geometry import _euler_from_matrix
from .model import WALL_GAP
from .validate import _fail, _fmt, _num

# ----------------------------------------------------------------------------------------
# Pair search and the Perram-Wertheim contact function
# ----------------------------------------------------------------------------------------
def _candidate_pairs(c, rb, period):
    """Pairs (i, j, shift) whose bounding spheres (radii rb) overlap, the image c[j] + shift
    being the one that does.  i < j, or i == j with shift != 0 (a periodic self-image)."""
    from scipy.spatial import cKDTree

    n = len(c)
    empty = (np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3)))
    if n == 0:
        return empty
    rmax = float(rb.max())
    if period is None:
        if n < 2:
            return empty
        ij = cKDTree(c).query_pairs(2.0 * rmax, output_type="ndarray")
        i, j = ij[:, 0], ij[:, 1]
        shift = np.zeros((len(i), 3))
    elif 2.0 * rmax < 0.499 * period:
        L = float(period)
        w = np.mod(c, L)
        w[w >= L] = 0.0
        ij = cKDTree(w, boxsize=L).query_pairs(2.0 * rmax, output_type="ndarray")
        i, j = ij[:, 0], ij[:, 1]
        d0 = c[j] - c[i]
        shift = -L * np.round(d0 / L)
    else:
        L = float(period)
        offs = L * np.array([(a, b, d) for a in (-1, 0, 1) for b in (-1, 0, 1) for d in (-1, 0, 1)], float)
        ii, jj, ss = [], [], []
        for a in range(n):
            js = np.arange(a, n)
            d = c[js][:, None, :] + offs[None] - c[a]
            hit = np.linalg.norm(d, axis=-1) < rb[a] + rb[js][:, None]
            same = js[:, None] == a
            # a self-image: keep one of +shift / -shift (and never the zero shift)
            lexpos = (offs[:, 0] > 0) | ((offs[:, 0] == 0) & (offs[:, 1] > 0)) | \
                     ((offs[:, 0] == 0) & (offs[:, 1] == 0) & (offs[:, 2] > 0))
            hit &= ~same | lexpos[None, :]
            jk, ok = np.nonzero(hit)
            ii.append(np.full(len(jk), a))
            jj.append(js[jk])
            ss.append(offs[ok])
        i, j, shift = np.concatenate(ii), np.concatenate(jj), np.concatenate(ss)
    if len(i):
        d = np.linalg.norm(c[j] + shift - c[i], axis=1)
        keep = d <= (rb[i] + rb[j]) * (1.0 + 1e-9)      # touching counts
        i, j, shift = i[keep], j[keep], shift[keep]
        order = np.lexsort((j, i))
        i, j, shift = i[order], j[order], shift[order]
    return i.astype(int), j.astype(int), shift


def _pw(r, MA, MB, iters=44):
    """Perram-Wertheim contact function of ellipsoids {x : x^T MA^-1 x <= 1} and the same with MB
    around r (MA = R diag(a^2) R^T).  Returns mu (both scaled by mu they touch: mu < 1 overlap),
    the optimal lambda and y = C(lambda)^-1 r for the derivatives."""
    L = np.linalg.cholesky(MA)
    Li = np.linalg.inv(L)
    K = Li @ MB @ np.swapaxes(Li, -1, -2)
    k, Q = np.linalg.eigh(K)
    z = np.einsum("pji,pj->pi", Q, np.einsum("pij,pj->pi", Li, r))
    z2 = z * z
    lo = np.zeros(len(r))
    hi = np.ones(len(r))
    for _ in range(iters):     # F(lambda) is concave: bisection on F'
        lam = 0.5 * (lo + hi)
        lm = lam[:, None]
        d = 1.0 - lm + lm * k
        fp = np.sum(z2 * (1.0 - 2.0 * lm - (k - 1.0) * lm * lm) / (d * d), axis=1)
        pos = fp > 0
        lo = np.where(pos, lam, lo)
        hi = np.where(pos, hi, lam)
    lam = 0.5 * (lo + hi)
    d = 1.0 - lam[:, None] + lam[:, None] * k
    F = lam * (1.0 - lam) * np.sum(z2 / d, axis=1)
    y = np.einsum("pji,pj->pi", Li, np.einsum("pij,pj->pi", Q, z / d))
    return np.sqrt(np.maximum(F, 0.0)), lam, y


def _ellipsoid_matrices(rot, axes):
    """M = R diag(axes^2) R^T for (N, 3, 3) rotations and (N, 3) semi-axes."""
    return np.einsum("nij,nj,nkj->nik", rot, axes ** 2, rot)


def _arrays(vesicles):
    c = np.array([v.center for v in vesicles], float).reshape(-1, 3)
    rot = np.array([v.rotation_matrix() for v in vesicles]).reshape(-1, 3, 3)
    scale = np.array([v.scale for v in vesicles])
    units = [v._unit for v in vesicles]
    enc = np.array([u.axes for u in units], float).reshape(-1, 3) * scale[:, None]
    rb = np.array([u.rbound for u in units]) * scale
    return c, rot, scale, units, enc, rb


def _sampled_overlap(ua, ca, Ra, ka, ub, cb, Rb, kb) -> bool:
    """Surface samples of A strictly inside B, or of B inside A."""
    for (u1, c1, R1, k1), (u2, c2, R2, k2) in (((ua, ca, Ra, ka), (ub, cb, Rb, kb)),
                                               ((ub, cb, Rb, kb), (ua, ca, Ra, ka))):
        x = c1 + (k1 * u1.surface_points()) @ R1.T          # world points of 1
        near = np.sum((x - c2) ** 2, axis=1) < (k2 * u2.rbound) ** 2
        if not near.any():
            continue
        xb = ((x[near] - c2) @ R2) / k2                      # body frame of 2
        if u2.inside(xb).any():
            return True
    return False


def find_overlaps(vesicles, period=None, first_only=False):
    """Overlapping (or touching) pairs of vesicles, sorted: a list of (i, j, shift, mu) with
    j's image at center + shift; i == j means a vesicle overlaps its own periodic image.
    mu is the Perram-Wertheim scale factor (< 1) for two quadrics, None for a sampled pair."""
    vesicles = list(vesicles)
    if not vesicles:
        return []
    c, rot, scale, units, enc, rb = _arrays(vesicles)
    i, j, shift = _candidate_pairs(c, rb, period)
    if len(i) == 0:
        return []
    M = _ellipsoid_matrices(rot, enc)
    r = c[j] + shift - c[i]
    mu, _, _ = _pw(r, M[i], M[j])
    exact = np.array([units[a].kind == "quadric" and units[b].kind == "quadric" for a, b in zip(i, j)], bool)
    out = []
    for n in np.nonzero(mu < 1.0 + 1e-9)[0]:
        a, b = int(i[n]), int(j[n])
        if exact[n]:
            out.append((a, b, shift[n], float(mu[n])))
        elif _sampled_overlap(units[a], c[a], rot[a], scale[a], units[b], c[b] + shift[n], rot[b], scale[b]):
            out.append((a, b, shift[n], None))
        if first_only and out:
            break
    return out


def check_overlaps(vesicles, period=None):
    """Raise SceneError naming the first overlapping pair (vesicle indices in the flat list)."""
    vesicles = list(vesicles)
    if period is not None and vesicles:
        total = sum(v.volume for v in vesicles)
        if total > period ** 3:
            _fail("domain.period", f"the vesicles' total volume {_num(total)} exceeds the periodic cell "
                                   f"({_num(period ** 3)}): they must overlap", period)
    found = find_overlaps(vesicles, period, first_only=True)
    if not found:
        return
    a, b, shift, mu = found[0]

    def name(k):
        lab = vesicles[k].label
        return f"vesicle[{k}]" + (f" ({lab})" if lab and lab != f"vesicle[{k}]" else "")

    va, vb = vesicles[a], vesicles[b]
    d = float(np.linalg.norm(np.asarray(vb.center) + shift - np.asarray(va.center)))
    across = "" if not np.any(shift) else f" across the periodic boundary (image shifted by {_fmt([_num(x) for x in shift]).replace(chr(34), '')})"
    if a == b:
        _fail(name(a), f"overlaps its own periodic image: its extent (bounding radius {_num(va.bounding_radius)}) "
                       f"does not fit in domain.period = {_num(period)}")
    if mu is not None:
        if mu >= 1.0 - 1e-6:
            fix = "they touch; move them apart a little"
        elif mu > 1e-12:
            fix = f"they need about {_num(d / mu)} along that line"
        else:
            fix = "they share the same centre"
        why = f"centres {_num(d)} apart, {fix}"
    else:
        why = (f"centres {_num(d)} apart, surface points of one lie inside the other "
               f"(bounding radii {_num(va.bounding_radius)}, {_num(vb.bounding_radius)})")
    err = SceneError(f"{name(a)} and {name(b)} overlap{across}: {why}")
    err.key = f"vesicle[{a}]"
    raise err


# ----------------------------------------------------------------------------------------
# Random packing: relax overlapping enclosing ellipsoids (projection of the contact
# constraints, translations and rotations), Jacobi-style and vectorized
# ----------------------------------------------------------------------------------------
def _rotvec_matrices(w):
    th = np.linalg.norm(w, axis=1)
    k = w / np.where(th > 0, th, 1.0)[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, cth = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3) + s * K + (1.0 - cth) * (K @ K)


def _random_packing(ves0, origin, box, periodic, gap, rng, key, phi, rotate=True, max_iter=None):
    """Centres and Euler angles of a non-overlapping packing of the vesicles ves0 (their shapes,
    sizes and orientations given) in the box [origin, origin + box), periodic or walled."""
    n = len(ves0)
    _, rot, scale, units, enc, rb = _arrays(ves0)
    enc = enc * (1.0 + gap)
    rb = rb * (1.0 + gap)
    ext = np.max(enc, axis=1)
    if periodic:
        if 2.0 * ext.max() >= box[0]:
            _fail(key, f"a vesicle (extent {_num(2 * ext.max())}) does not fit in the periodic cell", phi)
    elif np.any(2.0 * ext.max() >= box):
        _fail(key, f"a vesicle (extent {_num(2 * ext.max())}) does not fit in the box {_fmt([_num(b) for b in box])}", phi)
    # initial centres: best of a few random candidates (largest clearance to those placed)
    c = np.empty((n, 3))
    for a in range(n):
        if periodic:
            cand = origin + rng.uniform(size=(8, 3)) * box
        else:
            cand = origin + ext[a] + rng.uniform(size=(8, 3)) * (box - 2 * ext[a])
        if a == 0:
            c[a] = cand[0]
            continue
        d = cand[:, None, :] - c[None, :a, :]
        if periodic:
            d -= box * np.round(d / box)
        clear = np.min(np.linalg.norm(d, axis=-1) - rb[None, :a], axis=1) - rb[a]
        c[a] = cand[int(np.argmax(clear))]
    R = rot.copy()
    ell = rb.copy()                       # length scale of a rotation
    period = box[0] if periodic else None
    max_sweeps = max_iter or 1500
    target = 1.0 + 1e-3
    sweeps, stall, best, fewest, since_fewest = 0, 0, np.inf, np.inf, 0
    while True:
        if not periodic:
            h = np.sqrt(np.einsum("nij,nj,nij->ni", R, enc ** 2, R))   # half extents along x, y, z
            c = np.clip(c, origin + h, origin + box - h)
        i, j, shift = _candidate_pairs(c, rb, period)
        M = _ellipsoid_matrices(R, enc)
        r = c[j] + shift - c[i]
        mu, lam, y = _pw(r, M[i], M[j]) if len(i) else (np.zeros(0), np.zeros(0), np.zeros((0, 3)))
        nbad = int(np.sum(mu < 1.0))
        if nbad == 0:
            break
        sweeps += 1
        fewest, since_fewest = (nbad, 0) if nbad < fewest else (fewest, since_fewest + 1)
        if sweeps > max_sweeps or since_fewest > 400:
            fill = float(np.sum(4.0 / 3.0 * np.pi * np.prod(enc, axis=1)) / np.prod(box))
            _fail(key, f"random packing of {n} vesicles did not converge ({nbad} overlapping pairs left after "
                       f"{sweeps} sweeps): their enclosing ellipsoids, inflated by 1 + gap, would fill "
                       f"{fill:.3f} of the {'periodic cell' if periodic else 'box'} (random packings jam near "
                       "0.6-0.7); lower volume_fraction or gap, or use a regular lattice (count + spacing)", phi)
        worst = float(1.0 - mu.min())
        best, stall = (worst, 0) if worst < best * 0.999 else (best, stall + 1)
        sel = mu < target
        i, j, r, mu, lam, y = i[sel], j[sel], r[sel], mu[sel], lam[sel], y[sel]
        lm = lam[:, None]
        mus = np.maximum(mu, 1e-6)[:, None]
        g_r = lm * (1.0 - lm) * y / mus                                  # d mu / d c_j
        g_wi = -lm * (1.0 - lm) ** 2 * np.cross(np.einsum("pij,pj->pi", M[i], y), y) / mus
        g_wj = -lm ** 2 * (1.0 - lm) * np.cross(np.einsum("pij,pj->pi", M[j], y), y) / mus
        wi, wj = (1.0 / ell[i] ** 2, 1.0 / ell[j] ** 2) if rotate else (0.0 * ell[i], 0.0 * ell[j])
        den = 2.0 * np.sum(g_r ** 2, 1) + wi * np.sum(g_wi ** 2, 1) + wj * np.sum(g_wj ** 2, 1)
        step = ((target + 0.01 - mu) / np.maximum(den, 1e-300))[:, None]
        tiny = np.linalg.norm(r, axis=1) < 1e-9 * ell[i]                 # coincident centres
        if tiny.any():
            g_r[tiny] = rng.normal(size=(int(tiny.sum()), 3))
            step[tiny] = 0.1 * ell[i][tiny, None]
        dc = np.zeros((n, 3))
        dw = np.zeros((n, 3))
        cnt = np.zeros(n)
        np.add.at(dc, j, step * g_r)
        np.add.at(dc, i, -step * g_r)
        np.add.at(dw, i, step * wi[:, None] * g_wi)
        np.add.at(dw, j, step * wj[:, None] * g_wj)
        np.add.at(cnt, i, 1.0)
        np.add.at(cnt, j, 1.0)
        relax = 1.0 / np.sqrt(np.maximum(cnt, 1.0))[:, None]             # Jacobi: damp shared moves
        dw = np.clip(dw * relax, -0.3, 0.3)
        c = c + dc * relax
        if stall > 20:                    # jiggle the overlapping ones to leave a jammed state
            c += rng.normal(scale=0.02, size=(n, 3)) * ell[:, None] * (cnt > 0)[:, None]
            stall = 0
        R = _rotvec_matrices(dw) @ R
        if periodic:
            c = origin + np.mod(c - origin, box)
    _random_packing.sweeps = sweeps
    eul = [_euler_from_matrix(Rk) for Rk in R]
    return c, eul


def wall_distance(wall, points):
    """Signed distances (P,) of points (P, 3) to a [wall] container (scene.model.Wall), negative
    inside: exact for a sphere; for an ellipsoid the distance to dense samples of its surface
    (192 x 256, in its body frame), signed by the inside test."""
    x = (np.asarray(points, dtype=float) - np.asarray(wall.center)) @ wall.rotation_matrix()   # body frame
    a = np.asarray(wall.axes)
    if wall.shape == "sphere":
        return np.linalg.norm(x, axis=-1) - a[0]
    from scipy.spatial import cKDTree

    samples = _ellipsoid_samples(tuple(a))
    d, _ = cKDTree(samples).query(x)
    return np.where(np.sum((x / a) ** 2, axis=-1) < 1.0, -d, d)


@lru_cache(maxsize=8)
def _ellipsoid_samples(axes, nt=192, nphi=256):
    t = (np.arange(nt) + 0.5) * np.pi / nt
    f = np.arange(nphi) * 2.0 * np.pi / nphi
    tt, ff = np.meshgrid(t, f, indexing="ij")
    return np.stack([axes[0] * np.sin(tt) * np.cos(ff), axes[1] * np.sin(tt) * np.sin(ff),
                     axes[2] * np.cos(tt)], axis=-1).reshape(-1, 3)


def check_inside_wall(vesicles, wall):
    """SceneError unless every vesicle's bounding sphere lies inside the [wall] container with a
    gap of WALL_GAP times its radius."""
    c = np.array([v.center for v in vesicles], dtype=float)
    rb = np.array([v.bounding_radius for v in vesicles])
    gap = -wall_distance(wall, c) - rb
    need = WALL_GAP * np.array([v.radius for v in vesicles])
    bad = np.flatnonzero(gap < need)
    if len(bad):
        k = int(bad[0])
        v = vesicles[k]
        where = "outside the container" if gap[k] + rb[k] <= 0 else "crossing the wall or too close to it"
        _fail(v.label or f"vesicle[{k}]", f"centre {_fmt(list(v.center))}, bounding radius {rb[k]:.4g}: {where} "
              f"([wall] {wall.shape}, centre {_fmt(list(wall.center))}); its distance to the wall must be at least "
              f"{WALL_GAP:g} of its radius ({need[k]:.3g}), is {gap[k]:.3g}"
              + (f" ({len(bad)} vesicles)" if len(bad) > 1 else ""))


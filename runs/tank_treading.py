"""Tank-treading of one vesicle in shear: inclination angle and membrane rotation (docs/explanation/dynamics.md).

Runs the scene runs/tank_treading.toml (prolate, v = 0.9, lambda = 1, kappa_b = 0.1, shear
u = (z, 0, 0) of rate 1, p = 12) with the ordinary adaptive driver (vesflow.simulation.Run:
doubling error estimate, area/volume correction, reparameterization) and records after every
accepted step

* the inclination angle: the angle in the shear plane x-z between the flow direction x and
  the longest principal axis of the gyration tensor of the enclosed volume,
  int_V r r^T dV = (1/5) int_S r r^T (r . n) dA, r = x - centroid;
* a material marker: the grid points move with the fluid during a step (X^{n+1} = X^n + dt u),
  so a marker keeps its parameter (theta, phi) through the step; the area/volume correction
  and the reparameterization move the surface under it, after which the marker's spatial
  position is projected back onto the surface (least squares in tangent coordinates of the
  parameter sphere, so the parametric poles are harmless).  Its phase psi is the clockwise
  angle of (x - centroid) in the x-z plane (the sense of the shear's vorticity), unwrapped;
  the membrane rotation period is the time between successive passes of psi through the same
  value (mod 2 pi);
* the instantaneous tank-treading period of the membrane velocity field on the cross-section
  y = 0 (the marker's orbit once the shape is steady):  T = closed integral d alpha / omega(alpha),
  omega = d alpha / dt of a membrane point at polar angle alpha about the centroid;
* the r^2-weighted mean angular velocity int (r x v)_y dA / int (r_x^2 + r_z^2) dA (a rigid
  rotation's rate; for an elongated tank-treading shape it is a little below 2 pi / T).

    OMP_NUM_THREADS=1 .venv/bin/python runs/tank_treading.py                 # p = 12, T = 40
    OMP_NUM_THREADS=1 .venv/bin/python runs/tank_treading.py --p 8 --horizon 5 --png /tmp/tt.png
    OMP_NUM_THREADS=1 .venv/bin/python runs/tank_treading.py --replot         # figure from the saved series

The series are saved to out/tank_treading.npz; the figure goes to docs/img/tank_treading.png.
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


# ---------------------------------------------------------------------------------------- geometry
def gyration_tensor(surface):
    """Volume second moments about the centroid, (N, 3, 3)."""
    g = surface.geometry(2 * surface.p)
    c = surface.centroid()
    r = g.X - c[:, None, :]
    rn = np.einsum("nik,nik->ni", r, g.normal)
    return np.einsum("nia,nib,ni,ni->nab", r, r, rn, g.dA) / 5.0


def inclination_angle(surface):
    """Angle (radians, in (-pi/2, pi/2]) from x to the longest principal axis of the x-z block of the
    gyration tensor (the shear-plane section), measured toward z; and the equivalent-ellipsoid semi-axes
    sqrt(5 lambda_k / V) of the full tensor, longest first.  The scene is symmetric in y, so the tensor
    has no xy, yz entries and the x-z block's axis is a principal axis of the vesicle."""
    G = gyration_tensor(surface)[0]
    w2, V2 = np.linalg.eigh(G[np.ix_([0, 2], [0, 2])])
    e = V2[:, -1]
    a = np.arctan2(e[1], e[0])
    if a > np.pi / 2:
        a -= np.pi
    elif a <= -np.pi / 2:
        a += np.pi
    w = np.linalg.eigvalsh(G)
    return a, np.sqrt(w[::-1] * 5.0 / surface.volume()[0])


def centroid_velocity(surface, u_grid, q):
    """d(centroid)/dt = (1/V) int_S x (u . n) dA for a divergence-free u."""
    g = surface.geometry(q)
    un = np.einsum("nik,nik->ni", u_grid, g.normal)
    return np.einsum("nik,ni,ni->nk", g.X, un, g.dA)[0] / surface.volume()[0]


def rotation_measures(surface, u_coeffs):
    """(tank-treading period of the y = 0 section, r^2-weighted angular velocity, min omega on the section)."""
    from vesflow import sph
    p = surface.p
    # r^2-weighted mean angular velocity on the q = 2p grid
    q = 2 * p
    g = surface.geometry(q)
    ug = np.moveaxis(sph.transform(p, q).synth(u_coeffs), -2, -1)
    c = surface.centroid()[0]
    Uc = centroid_velocity(surface, ug, q)
    r = g.X[0] - c
    v = ug[0] - Uc
    lz = r[:, 2] * v[:, 0] - r[:, 0] * v[:, 2]
    rr = r[:, 0] ** 2 + r[:, 2] ** 2
    omega_w = float((lz * g.dA[0]).sum() / (rr * g.dA[0]).sum())
    # the y = 0 section on a fine grid: sign changes of y along rings and meridians
    qf = 4 * p
    Tf = sph.transform(p, qf)
    nlat, nlon = qf + 1, 2 * qf
    X = Tf.synth(surface.coeffs)[0].reshape(3, nlat, nlon) - c[:, None, None]
    U = Tf.synth(u_coeffs)[0].reshape(3, nlat, nlon) - Uc[:, None, None]
    P, W = [], []
    for Xa, Ua, Xb, Ub in ((X, U, np.roll(X, -1, axis=2), np.roll(U, -1, axis=2)),      # along rings
                           (X[:, :-1], U[:, :-1], X[:, 1:], U[:, 1:])):                # along meridians
        ya, yb = Xa[1], Xb[1]
        hit = (ya == 0) | (ya * yb < 0)
        s = np.where(hit, ya / np.where(hit, ya - yb, 1.0), 0.0)[hit]
        P.append((Xa[:, hit] + s * (Xb[:, hit] - Xa[:, hit])).T)
        W.append((Ua[:, hit] + s * (Ub[:, hit] - Ua[:, hit])).T)
    P, W = np.concatenate(P), np.concatenate(W)
    alpha = np.arctan2(P[:, 2], P[:, 0])
    om = (P[:, 2] * W[:, 0] - P[:, 0] * W[:, 2]) / (P[:, 0] ** 2 + P[:, 2] ** 2)
    order = np.argsort(alpha)
    alpha, om = alpha[order], om[order]
    if om.min() <= 0:
        return np.nan, omega_w, float(om.min())
    a = np.concatenate([alpha, [alpha[0] + 2 * np.pi]])
    f = 1.0 / np.concatenate([om, [om[0]]])
    period = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(a)))
    return period, omega_w, float(om.min())


class Marker:
    """A material point: parameter direction s (unit 3-vector) on the parameter sphere."""

    def __init__(self, surface, target):
        from vesflow import sph
        p = surface.p
        T = sph.transform(p)
        X = np.moveaxis(T.synth(surface.coeffs)[0], 0, -1)
        k = int(np.argmin(np.linalg.norm(X - target, axis=1)))
        i, j = divmod(k, T.nlon)
        th, ph = T.theta[i], T.phi[j]
        self.s = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
        self.s, self.residual = self.project(surface.coeffs, p, target)

    @staticmethod
    def position_at(coeffs, p, s):
        from vesflow import sph
        th = np.arccos(np.clip(s[2], -1.0, 1.0))
        ph = np.arctan2(s[1], s[0])
        return sph.evaluate(coeffs[0], p, [th], [ph])[:, 0]

    def position(self, coeffs, p):
        return self.position_at(coeffs, p, self.s)

    def project(self, coeffs, p, target):
        """Parameter of the surface point nearest to target, starting from the current one."""
        from scipy.optimize import least_squares
        s0 = self.s / np.linalg.norm(self.s)
        e1 = np.cross(s0, [1.0, 0.0, 0.0] if abs(s0[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(s0, e1)

        def s_of(ab):
            s = s0 + ab[0] * e1 + ab[1] * e2
            return s / np.linalg.norm(s)

        res = least_squares(lambda ab: self.position_at(coeffs, p, s_of(ab)) - target, np.zeros(2),
                            method="lm", xtol=1e-14, ftol=1e-14)
        return s_of(res.x), float(np.linalg.norm(res.fun))


# ---------------------------------------------------------------------------------------- the run
def make_run(scene, opts):
    from vesflow.simulation import Run

    class TrackedRun(Run):
        """Run that records the diagnostics above after every accepted step."""

        def start_tracking(self):
            S = self.stepper.surface
            c = S.centroid()[0]
            self.marker = Marker(S, c + np.array([0.0, 0.0, 3.0]))    # the top of the section y = 0
            self.series = {k: [] for k in ("t", "dt", "incl", "axes", "marker", "centroid", "period",
                                           "omega_w", "omega_min", "proj_res", "area", "volume", "its", "wall")}
            self.wall0 = time.perf_counter()
            self._record(S, self.marker.position(S.coeffs, self.p), np.nan, np.nan, np.nan, 0.0, 0.0, 0)

        def _record(self, S, xm, period, omega_w, omega_min, res, dt, its):
            a, axes = inclination_angle(S)
            rec = self.series
            rec["t"].append(self.t)
            rec["dt"].append(dt)
            rec["incl"].append(a)
            rec["axes"].append(axes)
            rec["marker"].append(xm)
            rec["centroid"].append(S.centroid()[0])
            rec["period"].append(period)
            rec["omega_w"].append(omega_w)
            rec["omega_min"].append(omega_min)
            rec["proj_res"].append(res)
            rec["area"].append(S.area()[0])
            rec["volume"].append(S.volume()[0])
            rec["its"].append(its)
            rec["wall"].append(time.perf_counter() - self.wall0)

        def _post_step(self):
            st = self.stepper
            stepped = st.surface
            xm = self.marker.position(stepped.coeffs, self.p)             # material update of the marker
            period, omega_w, omega_min = rotation_measures(stepped, self.u)
            super()._post_step()                                          # correction + reparameterization
            S = st.surface
            self.marker.s, res = self.marker.project(S.coeffs, self.p, xm)
            last = self.rows[-1]
            self._record(S, self.marker.position(S.coeffs, self.p), period, omega_w, omega_min, res,
                         last[1], last[3])
            if self.monitor:
                self.log(f"  t={self.t:8.4f} incl={np.degrees(self.series['incl'][-1]):7.3f} deg  "
                         f"T_tt={period:8.4f}  omega_w={omega_w:.4f}  proj_res={res:.1e}")

    run = TrackedRun(scene, opts, writer=None, progress=False, monitor=False)
    run.start_tracking()
    return run


def marker_phase(series):
    r = np.asarray(series["marker"]) - np.asarray(series["centroid"])
    return -np.unwrap(np.arctan2(r[:, 2], r[:, 0]))      # clockwise in x-z: the shear's sense


def marker_periods(t, psi):
    """Times at which psi passes psi[0] + 2 pi k, and their differences."""
    k = np.arange(1, int((psi[-1] - psi[0]) // (2 * np.pi)) + 1)
    levels = psi[0] + 2 * np.pi * k
    crossings = np.interp(levels, psi, t) if np.all(np.diff(psi) > 0) else \
        np.array([t[np.argmax(psi >= L)] for L in levels])
    return crossings, np.diff(np.concatenate([[t[0]], crossings]))


def phase_periods(t, psi, n_ref=8):
    """Periods from several reference phases: for each psi_ref, the differences of pass times."""
    out = []
    for ref in psi[0] + 2 * np.pi * np.arange(n_ref) / n_ref:
        levels = np.arange(ref, psi[-1], 2 * np.pi)
        if len(levels) >= 2:
            tp = np.interp(levels, psi, t)
            out.append(np.column_stack([tp[1:], np.diff(tp)]))
    return np.concatenate(out) if out else np.zeros((0, 2))


def summarize(d):
    t = d["t"]
    T = t[-1]
    last = t >= 0.75 * T
    incl = np.degrees(d["incl"])
    psi = marker_phase(d)
    lines = []
    lines.append(f"run: p = {int(d['p'])}, kappa_b = {float(d.get('kappa', np.nan)):g}, "
                 f"adapt tol {float(d.get('adapt_tol', np.nan)):g}, horizon {T:g}, {len(t) - 1} accepted steps, mean dt {np.mean(d['dt'][1:]):.3g}, "
                 f"mean GMRES its/step (3 solves) {np.mean(d['its'][1:]):.1f}, wall {d['wall'][-1]:.0f} s")
    lines.append(f"inclination angle over the last quarter (t >= {0.75 * T:g}): mean {incl[last].mean():.3f} deg "
                 f"= {incl[last].mean() / 180:.4f} pi, std {incl[last].std():.1e} deg, "
                 f"range [{incl[last].min():.4f}, {incl[last].max():.4f}] deg")
    for frac in (0.5, 0.25):
        m = t >= (1 - frac) * T
        lines.append(f"  drift: mean over the last {frac:g} of the run {incl[m].mean():.3f} deg")
    P = d["period"][1:]
    m = last[1:]
    lines.append(f"tank-treading period of the y = 0 section (closed integral of d alpha / omega), last quarter: "
                 f"mean {np.nanmean(P[m]):.4f}, std {np.nanstd(P[m]):.2e}, range [{np.nanmin(P[m]):.4f}, {np.nanmax(P[m]):.4f}]"
                 f"  -> frequency 2 pi / T = {2 * np.pi / np.nanmean(P[m]):.4f}")
    W = d["omega_w"][1:]
    lines.append(f"r^2-weighted angular velocity, last quarter: mean {W[m].mean():.4f}, std {W[m].std():.2e} "
                 f"(2 pi / omega = {2 * np.pi / W[m].mean():.3f}); min omega on the section {d['omega_min'][1:][m].min():.4f}")
    cross, per = marker_periods(t, psi)
    lines.append(f"marker: {((psi[-1] - psi[0]) / (2 * np.pi)):.3f} revolutions; returns to its starting phase at t = "
                 + ", ".join(f"{c:.3f}" for c in cross) + "; periods " + ", ".join(f"{x:.3f}" for x in per))
    pp = phase_periods(t, psi)
    late = pp[pp[:, 0] >= 0.5 * T]
    if len(late):
        lines.append(f"marker periods from 8 reference phases, completed after t = {0.5 * T:g}: mean {late[:, 1].mean():.4f}, "
                     f"std {late[:, 1].std():.2e} ({len(late)} periods)")
    if len(t) > 4:
        mm = t >= 0.5 * T
        rate = np.polyfit(t[mm], psi[mm], 1)[0]
        lines.append(f"marker mean angular rate over the second half (linear fit): {rate:.4f} (2 pi / rate = {2 * np.pi / rate:.3f})")
    ax = d["axes"][-1]
    lines.append(f"final equivalent-ellipsoid semi-axes {ax[0]:.4f} {ax[1]:.4f} {ax[2]:.4f}; "
                 f"centroid drift {np.linalg.norm(d['centroid'][-1] - d['centroid'][0]):.2e}; "
                 f"area drift {d['area'][-1] / d['area'][0] - 1:.1e}, volume drift {d['volume'][-1] / d['volume'][0] - 1:.1e}; "
                 f"marker projection residual max {np.max(d['proj_res']):.1e}")
    return "\n".join(lines)


def plot(d, png, overlays=()):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    t = d["t"]
    T = t[-1]
    last = t >= 0.75 * T
    psi = marker_phase(d)
    psi = psi - psi[0]
    incl = np.degrees(d["incl"])
    fig, axs = plt.subplots(3, 1, figsize=(7.5, 8.5), sharex=True)
    ax = axs[0]
    ax.plot(t, incl, "C0-", label=str(d.get("label", "run")))
    for k, o in enumerate(overlays):
        ax.plot(o["t"], np.degrees(o["incl"]), f"C{4 + k}-", lw=0.9, label=str(o.get("label", f"overlay {k}")))
    ax.axhspan(18.0, 27.0, color="0.88", zorder=0, label="0.1 pi .. 0.15 pi (range quoted in the issue)")
    m = incl[last].mean()
    ax.annotate(f"settled: {m:.2f} deg = {m / 180:.3f} pi", (0.75 * T, m), (0.45 * T, m + 1.0), fontsize=9,
                arrowprops=dict(arrowstyle="->", lw=0.8))
    ax.set_ylabel("inclination angle (deg)")
    lo = min([16.0] + [np.degrees(o["incl"]).min() - 1 for o in overlays])
    ax.set_ylim(lo, 31)
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title(f"v = 0.9, lambda = 1, kappa_b = {float(d.get('kappa', 0.1)):g}, shear rate 1, "
                 f"p = {int(d['p'])}", fontsize=10)
    ax = axs[1]
    ax.plot(t, psi / (2 * np.pi), "C1-", label="material marker on y = 0")
    ax.set_ylabel("marker phase (revolutions)")
    for k in range(1, int(psi[-1] / (2 * np.pi)) + 1):
        ax.axhline(k, color="0.8", lw=0.8, zorder=0)
    pp = phase_periods(t, marker_phase(d))
    late = pp[pp[:, 0] >= 0.5 * T]
    if len(late):
        ax.text(0.02, 0.9, f"period (marker, t > {0.5 * T:g}): {late[:, 1].mean():.3f}", transform=ax.transAxes,
                fontsize=9, va="top")
    ax = axs[2]
    ax.plot(t, np.gradient(psi, t), "C1:", lw=0.9, label="marker d psi / dt")
    ax.plot(t[1:], 2 * np.pi / d["period"][1:], "C2-", lw=1.8, label="2 pi / T,  T = closed integral d alpha / omega (y = 0)")
    ax.plot(t[1:], d["omega_w"][1:], "C3--", label="r^2-weighted mean angular velocity")
    for k, o in enumerate(overlays):
        ax.plot(o["t"][1:], 2 * np.pi / o["period"][1:], f"C{4 + k}-", lw=0.9, label="2 pi / T, " + str(o.get("label", "")))
    ax.axhline(0.5, color="0.6", lw=0.8, ls=":")
    ax.text(0.2, 0.51, "sphere: 1/2", fontsize=8, color="0.4")
    ax.set_ylim(0.2, 1.0)
    ax.set_ylabel("membrane angular velocity")
    ax.set_xlabel("time (1 / shear rate)")
    ax.legend(loc="upper center", fontsize=8, ncol=1)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(png)), exist_ok=True)
    fig.savefig(png, dpi=110)
    print(f"figure: {png}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=os.path.join(HERE, "tank_treading.toml"))
    ap.add_argument("--p", type=int, default=None, help="spherical-harmonic degree (scene: 12)")
    ap.add_argument("--horizon", type=float, default=None, help="simulated time (scene: 30)")
    ap.add_argument("--adapt-tol", type=float, default=None, help="-ves_adapt_tol (default 0.01)")
    ap.add_argument("--kappa", type=float, default=None, help="bending modulus kappa_b (scene: 0.1, capillary number 10)")
    ap.add_argument("--shape", choices=("prolate", "oblate"), default=None, help="initial shape (scene: prolate)")
    ap.add_argument("--beta", type=float, default=None,
                    help="Euler angle beta (degrees) of the initial shape about y (scene: 60, i.e. a prolate at 30 deg)")
    ap.add_argument("--overlay", nargs="*", default=[], help="saved series drawn as thin lines in the figure")
    ap.add_argument("--npz", default=os.path.join(ROOT, "out", "tank_treading.npz"))
    ap.add_argument("--png", default=os.path.join(ROOT, "docs", "img", "tank_treading.png"))
    ap.add_argument("--replot", action="store_true", help="only summarize and plot the saved series")
    ap.add_argument("--monitor", action="store_true", help="one line per accepted step")
    a = ap.parse_args(argv)
    if not a.replot:
        import petsc4py
        petsc4py.init([])
        from vesflow import options
        from vesflow.scene import load_scene
        scene = load_scene(a.scene)
        over = {}
        if a.p is not None:
            over["-ves_p"] = a.p
        if a.horizon is not None:
            over["-ts_max_time"] = a.horizon
        if a.adapt_tol is not None:
            over["-ves_adapt_tol"] = a.adapt_tol
        getter = options.dict_getter(over)
        scene = options.apply_overrides(scene, getter)
        import dataclasses
        ves = scene.vesicles[0]
        if a.kappa is not None:
            ves = dataclasses.replace(ves, bending_modulus=a.kappa)
        if a.shape is not None:
            ves = dataclasses.replace(ves, shape=a.shape)
        if a.beta is not None:
            ves = dataclasses.replace(ves, rotation=(0.0, a.beta, 0.0))
        scene = dataclasses.replace(scene, vesicles=(ves,))
        opts = options.read_options(getter, scene)
        print(f"{scene.title}: p = {scene.p}, horizon {scene.time.horizon:g}, adapt tol {opts['adapt_tol']:g}, "
              f"loadavg {os.getloadavg()}")
        w0, c0 = time.perf_counter(), time.process_time()
        run = make_run(scene, opts)
        run.monitor = a.monitor
        run.run()
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        d = {k: np.asarray(v, dtype=float) for k, v in run.series.items()}
        d["p"] = np.array(scene.p)
        d["kappa"] = np.array(scene.vesicles[0].bending_modulus)
        d["label"] = np.array(f"{scene.vesicles[0].shape} start at {np.degrees(d['incl'][0]):.0f} deg, p = {scene.p}")
        d["adapt_tol"] = np.array(opts["adapt_tol"])
        os.makedirs(os.path.dirname(os.path.abspath(a.npz)), exist_ok=True)
        np.savez(a.npz, **d)
        print(f"wall {wall:.1f} s, cpu {cpu:.1f} s, loadavg {os.getloadavg()}, {run.counts['accepted']} accepted / "
              f"{run.counts['rejected']} rejected steps; stage times "
              + ", ".join(f"{k} {v:.1f}" for k, v in run.timers.as_dict().items()))
        print(f"series: {a.npz}")
    d = dict(np.load(a.npz))
    print(summarize(d))
    plot(d, a.png, [dict(np.load(f)) for f in a.overlay])


if __name__ == "__main__":
    main()

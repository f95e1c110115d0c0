#!/usr/bin/env python
"""The figures of a run file, as recorded in docs/: steps (accepted, rejected by reason), GMRES
iterations, area and volume drift, the smallest gap between vesicles in the frames, the
unwrapped centroid motion (periodic runs) and the per-stage wall-clock split (/timings).

    python postprocess/run_report.py out/run.h5 [--gaps]

--gaps: the smallest signed surface gap of every frame (vesflow.collision.min_gap, minimum
image in a periodic box; costs about one collision check per frame).  A file that a run is
still writing: HDF5_USE_FILE_LOCKING=FALSE python postprocess/run_report.py ...
"""
import argparse

import numpy as np

from vesflow.io import read_output


def report(path, gaps=False):
    out = read_output(path)
    st = out.steps
    acc = st["accepted"].astype(bool)
    names = out.reason_names
    lines = [f"{path}: {out.n_vesicles} vesicles, p = {out.p}, period = {out.periodic_length:g}, "
             f"{out.n_frames} frames to t = {out.time[-1]:.6g}"]
    rej = {names[int(r)]: int(np.sum(st["reason"][~acc] == r)) for r in np.unique(st["reason"][~acc])}
    why = f" {rej}" if rej else ""
    lines.append(f"steps    {int(acc.sum())} accepted, {int((~acc).sum())} rejected{why}; "
                 f"dt {st['dt'][acc].min():.3g} .. {st['dt'][acc].max():.3g}; "
                 f"GMRES iterations {int(st['ksp_its'].sum())} ({st['ksp_its'][acc].mean():.1f} per accepted step)")
    A, V = out.frames["area"], out.frames["volume"]
    lines.append(f"drift    area {np.abs(A / A[0] - 1).max():.2e}, volume {np.abs(V / V[0] - 1).max():.2e} "
                 "(max over vesicles and frames, relative to t = 0)")
    c = out.frames["centroid"]
    moved = np.linalg.norm(c - c[0], axis=-1)
    wraps = ""
    if "image" in out.frames:
        im = out.frames["image"]
        wraps = f"; {int(np.any(im[-1] != 0, axis=1).sum())} vesicles wrapped across a face (image != 0 at the end)"
    lines.append(f"centroid unwrapped displacement: mean {moved[-1].mean():.3g}, max {moved.max():.3g}{wraps}")
    if gaps:
        from vesflow.collision import min_gap
        from vesflow.surface import Surface
        g = [min_gap(Surface(cf, out.p), 2 * out.p, out.periodic_length or None)
             for cf in out.frames["coefficients"]]
        lines.append(f"gaps     smallest signed surface gap {min(g):.3g} (frame {int(np.argmin(g))}), "
                     f"at t = 0 {g[0]:.3g}, at the end {g[-1]:.3g}")
    t = out.timings
    keys = [k for k in ("setup", "self", "near", "far", "repar", "other") if k in t]
    tot = float(t.get("total", 0.0)) or 1.0
    lines.append("wall     total {:.1f} s: ".format(tot) + ", ".join(f"{k} {float(t[k]):.1f} ({100 * float(t[k]) / tot:.0f} %)"
                                                          for k in keys))
    n = max(int(acc.sum()), 1)
    lines.append(f"per accepted step {tot / n:.1f} s wall")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--gaps", action="store_true", help="the smallest surface gap of every frame")
    a = ap.parse_args(argv)
    print(report(a.run, a.gaps))


if __name__ == "__main__":
    main()

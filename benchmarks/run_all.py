"""Run every benchmark script of benchmarks/ with quick settings (`make bench`); exit 1 if one fails.

Each script runs in its own process (the Python running this file, the environment as given:
OMP_NUM_THREADS is passed through, the Makefile exports 2), its output is printed as it comes,
and a summary with the status and wall time of each follows.  The quick settings take a few
minutes on 2 cores; --full runs every script with its own defaults instead (the runs of
docs/explanation/performance.md, docs/explanation/far_field.md, docs/explanation/transforms.md, docs/explanation/dynamics.md: about an hour or more).  The one-off studies of experiments/ are not run.  sht_ducc0.py is skipped (and said so) when ducc0 does not import.

    .venv/bin/python benchmarks/run_all.py                     # what `make bench` runs
    .venv/bin/python benchmarks/run_all.py --only self_operator far_field
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/run_all.py --full
"""
import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))

# script, quick arguments, MPI ranks (0: run without mpiexec).  Every script of benchmarks/ is
# here (tests/packaging/test_layout.py checks it); one-off studies are in experiments/.
SCRIPTS = [
    ("sht_ducc0.py", ["--p", "8", "16", "--batch", "1", "100", "--repeat", "2"], 0),
    ("self_operator.py", ["--degrees", "8", "16", "--setup-ves", "1", "--stream-mb", "0", "--rounds", "3"], 0),
    ("far_field.py", ["--sizes", "4", "8", "16", "--repeat", "1", "--max-seconds", "60", "--budget", "120"], 0),
    ("ewald.py", ["--sizes", "8", "16", "--p", "8", "--q", "16", "--max-seconds", "20", "--budget", "60"], 0),
    ("setup_operators.py", ["--n", "4", "--p", "8", "--repeat", "1"], 0),
    ("iteration.py", ["--n", "8", "--p", "8", "--repeat", "1"], 0),
    ("pair_kernels.py", ["--repeat", "1", "--sources", "2000", "--blocks", "100"], 0),
    ("near_field.py", ["--cells", "2", "2", "8", "--p", "8", "--repeat", "1", "--its", "2"], 0),
    ("gmres_iterations.py", ["--sizes", "2", "8", "--degrees", "8"], 0),
    ("cost_model.py", ["--degrees", "6", "8", "--repeat", "1"], 0),
    ("step_cost.py", ["--p", "6", "--steps", "10"], 0),
    ("mpi_scaling.py", ["--nves", "8", "--p", "6", "--steps", "1"], 2),
    ("ewald_grid.py", ["--nves", "8", "--p", "4", "--q", "8", "--tol", "1e-6", "--repeat", "1"], 2),
    ("sdc_order.py", ["--p", "4", "--case", "prolate", "--dts", "0.1,0.05", "--schemes", "euler,sdc3x2"], 0),
    ("render_movie.py", ["--frames", "60"], 0),
    ("calibrate.py", ["--degrees", "6", "8", "--repeat", "1", "-o", os.path.join(tempfile.gettempdir(), "vesflow_calibration_quick.json")], 0),
    ("frame_cost.py", ["--p", "6", "--steps", "5"], 0),
    ("memory_per_vesicle.py", ["--nves", "4", "--p", "8", "--scenes", "free"], 0),
    ("contacts.py", ["--case", "pushed-0.3", "--schemes", "sdc"], 0),
]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--full", action="store_true", help="each script with its own (slow) defaults")
    ap.add_argument("--only", nargs="+", default=None, help="script names (with or without .py) to run")
    args = ap.parse_args(argv)
    only = None if args.only is None else {n if n.endswith(".py") else n + ".py" for n in args.only}
    unknown = (only or set()) - {s for s, _, _ in SCRIPTS}
    if unknown:
        ap.error(f"unknown scripts {sorted(unknown)}; known: {[s for s, _, _ in SCRIPTS]}")

    print(f"# benchmarks/run_all.py ({'full' if args.full else 'quick'} settings); python {sys.executable}; "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; {os.cpu_count()} cpus; "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    results = []
    for script, quick, ranks in SCRIPTS:
        if only is not None and script not in only:
            continue
        if script == "sht_ducc0.py" and importlib.util.find_spec("ducc0") is None:
            print(f"\n===== {script}: skipped (ducc0 does not import)", flush=True)
            results.append((script, "skipped (no ducc0)", 0.0))
            continue
        cmd = [sys.executable, os.path.join(HERE, script)] + ([] if args.full else quick)
        if ranks:
            cmd = [os.path.join(os.path.dirname(sys.executable), "mpiexec"), "-n", str(ranks)] + cmd
        shown = [os.path.relpath(c) if c.endswith(".py") else c for c in cmd if c != sys.executable]
        if ranks:
            shown[0] = "mpiexec"
        print(f"\n===== {' '.join(shown)}", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call(cmd, cwd=os.path.dirname(HERE))
        dt = time.perf_counter() - t0
        results.append((script, "ok" if rc == 0 else f"FAILED (exit status {rc})", dt))

    print("\n# summary")
    for script, status, dt in results:
        print(f"#   {script:<22} {status:<22} {dt:7.1f} s")
    print(f"# load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    failed = [s for s, status, _ in results if status.startswith("FAILED")]
    if failed:
        print(f"# {len(failed)} benchmark(s) failed: {', '.join(failed)}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""One thread policy for the OpenMP kernels and BLAS (issue 16; docs/explanation/performance.md, "Threads").

- OpenMP (the compiled kernels: far-field sums, near pairs, series at points): at most
  OMP_NUM_THREADS threads (the HPC convention; the Makefile exports 2), fewer while the load
  average says the other cores are busy (`adapt_openmp`, once per solve), and idle threads
  sleep instead of spinning (OMP_WAIT_POLICY=PASSIVE unless the user set it): a spinning
  thread takes the core that another process, or our own main thread, needs.
- Per-vesicle set-up (self operators, preconditioner blocks) runs on the same number of
  Python threads, one vesicle each (`map_vesicles`): numpy releases the GIL inside its
  array operations and BLAS calls, which is where that work is; only as many as there are
  idle cores (the machine's runnable threads right now), so that a shared machine is not
  oversubscribed.
- BLAS (numpy's OpenBLAS: the batched per-vesicle GEMV/GEMM of the self operators, the
  transforms, the block assembly and LU): one thread by default (-ves_blas_threads).  Its
  matrices are small and per vesicle: threads there cost more in start-up and busy-waiting
  than they save, and oversubscribe the cores the OpenMP kernels use next.

`early_environment` must run before numpy is imported and `configure` before the kernels
are (OpenBLAS and libgomp read their environment when they are loaded); vesflow.cli calls
both, in that order.  Library users who import vesflow directly get
the OpenMP and BLAS defaults of their environment until they call it.
"""
from __future__ import annotations

import os
import threading

_state = {"limiter": None, "blas": None, "pool": None, "controller": None}


def early_environment():
    """Before numpy is imported: OpenBLAS starts with one thread and OpenMP threads wait
    passively, unless the user set OPENBLAS_NUM_THREADS / OMP_WAIT_POLICY.  An OpenBLAS that
    starts with a pool of OMP_NUM_THREADS threads stays 10-15% slower after being limited to
    one at run time (p = 12 pair, OMP_NUM_THREADS=2: 3.0-3.1 s vs 2.5-2.6 s per 10 steps;
    with OPENBLAS_NUM_THREADS=1 set first: 3.7 / 3.7 s vs 3.7 / 3.7 s at that moment's load);
    `configure` raises it again when -ves_blas_threads asks for more."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def configure(blas_threads=1):
    """Set the policy above for this process; returns {'openmp': n, 'blas': n}."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import numpy  # noqa: F401  (numpy and scipy each carry an OpenBLAS: load both, then limit both)
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits
    _state["limiter"] = threadpool_limits(limits=int(blas_threads), user_api="blas")
    _state["blas"] = int(blas_threads)
    return {"openmp": openmp_threads(), "blas": int(blas_threads)}


def openmp_threads():
    """Threads the OpenMP kernels use (OMP_NUM_THREADS, else the number of cores)."""
    try:
        return max(1, int(os.environ.get("OMP_NUM_THREADS", "")))
    except ValueError:
        return os.cpu_count() or 1


def describe():
    """One line for the run's log."""
    blas = _state["blas"]
    return (f"threads: OpenMP {openmp_threads()} ({os.environ.get('OMP_WAIT_POLICY', 'default')} wait), "
            f"BLAS {blas if blas is not None else 'environment default'}")


def other_runnable():
    """Runnable threads of the machine right now besides this one (/proc/loadavg's running
    count less one; the 1-minute load average less one where /proc is not there)."""
    try:
        with open("/proc/loadavg") as f:
            return int(f.read().split()[3].split("/")[0]) - 1
    except (OSError, ValueError, IndexError):
        return os.getloadavg()[0] - 1.0


def free_cores():
    """Cores not busy with other work: the cores minus other_runnable(), at least 1.  (The
    1-minute load average lags a process that just started by a minute, which made two
    threads run 4-9% slower next to one busy process: p = 12 pair, measured.)"""
    ncpu = os.cpu_count() or 1
    return max(1, min(ncpu, int(ncpu - other_runnable() + 0.5)))


MIN_PAIRS_OPENMP = 5e5   # far-field source-target pairs below which one thread is faster


def adapt_openmp(pairs=None):
    """Set the OpenMP kernels' threads to min(OMP_NUM_THREADS, free_cores()) for what follows
    (Stepper.solve calls it once per solve): on a machine whose other cores are busy, threads
    that wait at the end of every parallel loop for a descheduled sibling only add time; and
    one thread when the far field has fewer than MIN_PAIRS_OPENMP source-target pairs (the
    kernels' loops are then too short to pay for waking a thread: two vesicles at p = 6, 1e5
    pairs, ran 7% slower on 2 threads of an idle machine)."""
    from ._kernels import series  # lazy: libgomp reads the OMP_ variables configure() sets when the kernels load
    n = min(openmp_threads(), free_cores())
    if pairs is not None and pairs < MIN_PAIRS_OPENMP:
        n = 1
    series.set_num_threads(n)
    return n


def blas_one_thread():
    """A context in which BLAS runs on one thread: for BLAS calls made from several Python
    threads at once (map_vesicles), each of which would otherwise wake its own BLAS threads
    to spin against the others' (N = 64 self operators at p = 16 on 2 threads, OpenBLAS left at 2
    threads: 0.17 s wall / 0.11 s CPU per apply instead of 0.04 / 0.026).  ~10 us."""
    if _state.get("controller") is None:
        from threadpoolctl import ThreadpoolController
        _state["controller"] = ThreadpoolController()
    return _state["controller"].limit(limits=1, user_api="blas")


MIN_P_THREADS = 10     # below this degree a vesicle's set-up is too small for a thread to pay
_POOL_PREFIX = "vesflow-pool"


def vesicle_threads(n_items):
    """Threads map_vesicles uses for n_items tasks: min(OMP_NUM_THREADS, n_items, free_cores())."""
    return max(1, min(openmp_threads(), int(n_items), free_cores()))


def map_vesicles(fn, items, p=None):
    """[fn(i) for i in items], on up to openmp_threads() Python threads (one item per task,
    results in order), but no more than free_cores(): on a machine whose other cores are busy
    the threads only contend (measured, p = 12 pair at load 6: 2 threads 5.6-8.0 s vs 1 thread
    4.5-4.9 s); in this thread when one is all there is, or when the degree p is below
    MIN_P_THREADS (idle machine, 2 threads vs 1: p = 6, 20 steps 0.74-0.78 s vs 0.69-0.70 s;
    p = 12: 2.75-3.12 s vs 3.79-3.89 s).  BLAS runs on one thread while the threads do
    (blas_one_thread), and on the n worker threads the OpenMP kernels (e.g. the self operators'
    kernel tables) run on openmp_threads() // n threads (one, with 2 and 2): the vesicles are
    the parallelism."""
    items = list(items)
    n = vesicle_threads(len(items))
    if p is not None and p < MIN_P_THREADS:
        n = 1
    if n <= 1 or threading.current_thread().name.startswith(_POOL_PREFIX):
        return [fn(i) for i in items]      # (called from one of the pool's own tasks: no nesting)
    pool = _state["pool"]
    if pool is None or pool._max_workers != n:
        from concurrent.futures import ThreadPoolExecutor
        if pool is not None:
            pool.shutdown(wait=False)
        pool = _state["pool"] = ThreadPoolExecutor(max_workers=n, thread_name_prefix=_POOL_PREFIX)
    from ._kernels import series  # lazy: libgomp reads the OMP_ variables configure() sets when the kernels load
    per_worker = max(1, openmp_threads() // n)

    def with_shared_openmp(i):     # no nested teams (2 x 2 threads on 2 cores): the OpenMP
        series.set_num_threads(per_worker)   # ICV is per calling thread: this worker's kernels
        return fn(i)
    with blas_one_thread():
        return list(pool.map(with_shared_openmp, items))

"""The thread policy (vesflow.threads, issue 16): BLAS limited to -ves_blas_threads, OpenMP
threads from OMP_NUM_THREADS with passive waiting, set by the run before the kernels load."""
import os
import subprocess
import sys

from threadpoolctl import threadpool_info

from vesflow import threads


def test_configure_limits_blas_and_sets_passive_openmp_waiting(monkeypatch):
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    try:
        got = threads.configure(1)
        import scipy.linalg  # noqa: F401  (scipy's own OpenBLAS: it too must be limited)
        blas = [p for p in threadpool_info() if p["user_api"] == "blas"]
        assert len(blas) >= 2 and all(p["num_threads"] == 1 for p in blas), blas
        assert got == {"openmp": 2, "blas": 1}
        assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE"
        assert "OpenMP 2 (PASSIVE wait), BLAS 1" in threads.describe()
    finally:
        threads._state["limiter"].restore_original_limits()


def test_a_run_sets_the_policy_before_the_kernels_are_loaded():
    """The CLI configures the threads before any compiled kernel (libgomp reads
    OMP_WAIT_POLICY when it is loaded); the user's own OMP_WAIT_POLICY wins."""
    code = ("import sys, vesflow.cli as c\n"
            "from vesflow import threads\n"
            "orig = threads.configure\n"
            "def spy(n):\n"
            "    assert not any(m.startswith('vesflow._kernels') for m in sys.modules), 'kernels loaded first'\n"
            "    assert os.environ['OPENBLAS_NUM_THREADS'] == '1'\n"
            "    print('configured', n); return orig(n)\n"
            "threads.configure = spy\n"
            "import os\n"
            "rc = c.main(['run', '-ves_p', '4', '-ts_max_steps', '1', '-ves_blas_threads', '2', '-o', sys.argv[1]])\n"
            "print('wait', os.environ['OMP_WAIT_POLICY']); sys.exit(rc)\n")
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        env = dict(os.environ, OMP_WAIT_POLICY="ACTIVE")
        env.pop("OPENBLAS_NUM_THREADS", None)
        r = subprocess.run([sys.executable, "-c", code, os.path.join(d, "t.h5")], capture_output=True, text=True,
                           env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "configured 2" in r.stdout and "wait ACTIVE" in r.stdout


def test_map_vesicles_keeps_order_and_uses_no_more_threads_than_free_cores(monkeypatch):
    import threading
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    names = set()

    def work(i):
        names.add(threading.current_thread().name)
        return i * i
    monkeypatch.setattr(threads, "other_runnable", lambda: 0)              # idle machine: 2 threads
    assert threads.free_cores() == 2
    assert threads.map_vesicles(work, range(7)) == [i * i for i in range(7)]
    assert names and all(n.startswith("vesflow") for n in names)
    names.clear()
    monkeypatch.setattr(threads, "other_runnable", lambda: 1)              # the other core is busy: serial
    assert threads.free_cores() == 1
    assert threads.map_vesicles(work, range(3)) == [0, 1, 4]
    assert names == {threading.current_thread().name}


def test_map_vesicles_runs_the_openmp_kernels_of_its_workers_on_one_thread():
    """No nested teams (2 Python threads x 2 OpenMP threads on 2 cores): in a process started
    with OMP_NUM_THREADS=2 (libgomp's default for new threads), the workers' kernels get one
    thread and the main thread keeps its two."""
    code = ("import os; from vesflow import threads; from vesflow._kernels import series\n"
            "os.cpu_count = lambda: 2; threads.other_runnable = lambda: 0\n"
            "seen = threads.map_vesicles(lambda i: series.get_max_threads(), range(6))\n"
            "print('workers', sorted(set(seen)), 'main', series.get_max_threads())\n")
    env = dict(os.environ, OMP_NUM_THREADS="2", PYTHONPATH=os.getcwd())
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "workers [1] main 2" in r.stdout, r.stdout


def test_openmp_threads_follow_the_idle_cores(monkeypatch):
    from vesflow._kernels import series
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    try:
        monkeypatch.setattr(threads, "other_runnable", lambda: 0)
        assert threads.adapt_openmp() == 2 and series.get_max_threads() == 2
        monkeypatch.setattr(threads, "other_runnable", lambda: 2)
        assert threads.adapt_openmp() == 1 and series.get_max_threads() == 1
    finally:
        series.set_num_threads(threads.openmp_threads())


def test_self_operators_apply_threaded_over_vesicle_ranges_equals_one_product(monkeypatch):
    """SelfOperators.apply splits the vesicles into one range per free thread (the same
    products, bit for bit); below MIN_BYTES_THREADED, or with one free core, it is one call."""
    import threading
    import numpy as np
    from vesflow.layerpot import singular
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    monkeypatch.setattr(threads, "other_runnable", lambda: 0)
    rng = np.random.default_rng(0)
    N, C = 5, 8
    ops = rng.standard_normal((N, 3 * C, 3 * C))
    x = rng.standard_normal((N, 3, C))
    ref = np.stack([(ops[v] @ x[v].reshape(-1)).reshape(3, C) for v in range(N)])
    calls = []
    real = np.matmul
    from threadpoolctl import threadpool_info, threadpool_limits

    def blas_threads():
        return max(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")

    def spy(a, b, out=None):
        calls.append((len(a), threading.current_thread().name, blas_threads()))
        return real(a, b, out=out)
    monkeypatch.setattr(singular.np, "matmul", spy)
    monkeypatch.setattr(singular, "MIN_BYTES_THREADED", 0)
    with threadpool_limits(limits=2, user_api="blas"):        # BLAS on one thread during the ranges only
        for dtype, tol in ((np.float64, 0.0), (np.float32, 1e-5)):
            calls.clear()
            u = singular.SelfOperators.apply(ops.astype(dtype), x)
            assert u.dtype == np.float64 and np.abs(u - ref).max() <= tol * np.abs(ref).max()
            assert sorted(n for n, _, _ in calls) == [2, 3] and all(t.startswith("vesflow") for _, t, _ in calls)
            assert [b for _, _, b in calls] == [1, 1] and blas_threads() == 2
    calls.clear()
    monkeypatch.setattr(singular, "MIN_BYTES_THREADED", ops.nbytes + 1)
    assert np.array_equal(singular.SelfOperators.apply(ops, x), ref)
    assert [n for n, _, _ in calls] == [N]
    calls.clear()
    monkeypatch.setattr(singular, "MIN_BYTES_THREADED", 0)
    monkeypatch.setattr(threads, "other_runnable", lambda: 1)                # the other core busy
    assert np.array_equal(singular.SelfOperators.apply(ops, x), ref) and [n for n, _, _ in calls] == [N]


def test_map_vesicles_called_from_its_own_task_runs_in_that_thread(monkeypatch):
    """A task of the pool that maps again (e.g. a self-operator apply inside a per-vesicle
    set-up) must not wait for the pool it occupies: the inner map runs in the task's thread."""
    import threading
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    monkeypatch.setattr(threads, "other_runnable", lambda: 0)

    def outer(i):
        me = threading.current_thread().name
        inner = threads.map_vesicles(lambda j: threading.current_thread().name, range(3))
        return i, inner == [me] * 3
    assert threads.map_vesicles(outer, range(4)) == [(i, True) for i in range(4)]

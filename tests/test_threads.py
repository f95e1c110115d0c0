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
        blas = [p for p in threadpool_info() if p["user_api"] == "blas"]
        assert blas and all(p["num_threads"] == 1 for p in blas)
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
            "    print('configured', n); return orig(n)\n"
            "threads.configure = spy\n"
            "import os\n"
            "rc = c.main(['run', '-ves_p', '4', '-ts_max_steps', '1', '-ves_blas_threads', '2', '-o', sys.argv[1]])\n"
            "print('wait', os.environ['OMP_WAIT_POLICY']); sys.exit(rc)\n")
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        env = dict(os.environ, OMP_WAIT_POLICY="ACTIVE")
        r = subprocess.run([sys.executable, "-c", code, os.path.join(d, "t.h5")], capture_output=True, text=True,
                           env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "configured 2" in r.stdout and "wait ACTIVE" in r.stdout

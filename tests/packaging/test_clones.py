"""Two clones on one machine each run their own code: tools/setup_env.sh gives each clone its
own .venv, layered on the one shared PETSc environment (tools/layered_venv.sh), with the
clone installed into it in editable mode; the shared environment is not changed."""
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.harness import ROOT, clean_env, shared_env


def run(cmd, cwd="/", **kw):
    r = subprocess.run([str(c) for c in cmd], cwd=cwd, env=clean_env(), capture_output=True, text=True, **kw)
    assert r.returncode == 0, f"{' '.join(map(str, cmd))}: exit {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    return r.stdout


def site_packages(python):
    return Path(run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"]).strip())


def listing(directory):
    """Names and modification times of a directory's entries (what an install would change)."""
    return sorted((p.name, p.stat().st_mtime_ns) for p in Path(directory).iterdir())


def test_layered_venv_sees_the_shared_environment_and_keeps_its_own_installs(tmp_path):
    shared = shared_env()
    venv = tmp_path / "venv"
    before = listing(site_packages(shared / "bin" / "python"))
    run([ROOT / "tools" / "layered_venv.sh", venv, shared])
    py = venv / "bin" / "python"
    site = site_packages(py)
    assert site.is_relative_to(venv) and (venv / "pyvenv.cfg").is_file() and not venv.is_symlink()
    assert (site / "_vesflow_shared_env.pth").read_text().strip() == str(site_packages(shared / "bin" / "python"))
    assert (venv / ".shared-env").read_text().strip() == str(shared)
    out = run([py, "-c", "import sys, petsc4py, numpy; from mpi4py import MPI; from petsc4py import PETSc; "
               "print(sys.prefix); print(MPI.Get_library_version()[:5])"]).split("\n")
    assert out[0] == str(venv)
    assert (venv / "bin" / "mpiexec").exists()
    pkg = tmp_path / "probe"                          # a package installed into the venv stays there
    (pkg / "vesflow_probe").mkdir(parents=True)
    (pkg / "vesflow_probe" / "__init__.py").write_text("")
    (pkg / "pyproject.toml").write_text('[project]\nname = "vesflow-probe"\nversion = "1"\n'
                                        '[build-system]\nrequires = ["setuptools"]\nbuild-backend = "setuptools.build_meta"\n')
    run([py, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index", pkg], cwd=tmp_path)
    assert run([py, "-c", "import vesflow_probe; print(vesflow_probe.__file__)"]).startswith(str(site))
    assert listing(site_packages(shared / "bin" / "python")) == before
    r = subprocess.run([ROOT / "tools" / "layered_venv.sh", venv, shared], capture_output=True, text=True)
    assert r.returncode == 2 and "exists" in r.stderr


def make_clone(dst):
    """A copy of the tree's files (tracked and new, as git sees them) and of its built kernels
    (newer than their sources: the editable install does not compile them again)."""
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, check=True,
                           capture_output=True).stdout.decode().split("\0")
    for f in filter(None, files):
        if (ROOT / f).is_file():
            (dst / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / f, dst / f)
    kernels = ROOT / "vesflow" / "_kernels"
    for built in sorted(kernels.glob("*.c")) + sorted(kernels.glob("*.so")):    # the .so last: newest
        shutil.copy(built, dst / "vesflow" / "_kernels" / built.name)
    return dst


@pytest.mark.slow
def test_two_clones_set_up_on_one_machine_each_import_their_own_tree(tmp_path):
    shared = shared_env()
    before = listing(site_packages(shared / "bin" / "python"))
    clones = {name: make_clone(tmp_path / name) for name in ("a", "b")}
    env = clean_env(VESFLOW_ENV=str(shared))
    for name, clone in clones.items():             # a first, then b: b must not take over a's .venv
        (clone / "vesflow" / "__init__.py").open("a").write(f"\nCLONE = {name!r}\n")
        r = subprocess.run([clone / "tools" / "setup_env.sh"], cwd=clone, env=env, capture_output=True, text=True)
        assert r.returncode == 0, r.stdout + r.stderr
        assert "ready:" in r.stdout
    for name, clone in clones.items():
        py = clone / ".venv" / "bin" / "python"
        assert not (clone / ".venv").is_symlink()
        out = run([py, "-c", "import vesflow, vesflow._kernels.stokes as k; print(vesflow.CLONE); "
                   "print(vesflow.__file__); print(k.__file__)"]).split()
        assert out[0] == name and all(Path(p).is_relative_to(clone) for p in out[1:])
        assert "usage: vesflow run" in run([clone / ".venv" / "bin" / "vesflow", "--help"])
    assert listing(site_packages(shared / "bin" / "python")) == before
    # set up again: nothing to do, the same .venv
    r = subprocess.run([clones["a"] / "tools" / "setup_env.sh"], cwd=clones["a"], env=env, capture_output=True,
                       text=True)
    assert r.returncode == 0 and "building" not in r.stdout and "creating" not in r.stdout

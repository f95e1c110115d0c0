"""Packaging: every third-party package vesflow/ imports is declared in pyproject.toml; the
built wheel, installed (not editable) into a fresh venv layered on the shared PETSc
environment, runs `vesflow check`, `run`, `render` and `export` from a directory outside the
tree; `vesflow render` without the render extra says which package is missing."""
import ast
import importlib.metadata as md
import re
import shutil
import subprocess
import sys
import tomllib
import pytest

from tests.harness import ROOT, clean_env, shared_env
from vesflow import cli

def _norm(name):
    return re.sub(r"[-_.]+", "-", name).lower()


def _declared():
    """{distribution: where} of pyproject.toml: "core" or the extra's name."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    out = {}
    for where, reqs in [("core", project["dependencies"])] + list(project["optional-dependencies"].items()):
        for r in reqs:
            out.setdefault(_norm(re.match(r"[A-Za-z0-9_.\-]+", r).group(0)), where)
    return out


def _imported():
    """{top-level module: [files]} of the absolute imports in vesflow/*.py outside the standard library."""
    out = {}
    for path in sorted((ROOT / "vesflow").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module]
            else:
                continue
            for n in names:
                top = n.split(".")[0]
                if top not in sys.stdlib_module_names and top not in ("vesflow", "__future__"):
                    out.setdefault(top, []).append(str(path.relative_to(ROOT)))
    return out


# optional: imported only where their absence is handled (the extra they belong to)
OPTIONAL = {"fmm3dpy": "fmm", "tomli": "core"}


def _dists_of(module, table):
    """The installed distributions providing a top-level module (packages_distributions misses
    compiled top-level modules without top_level.txt, e.g. ducc0: then a distribution of that name)."""
    if module in table:
        return table[module]
    try:
        return [md.distribution(module).metadata["Name"]]
    except md.PackageNotFoundError:
        return []


# the modules that may import the render extra's packages (vesflow render, vesflow export --vtk:
# both check them first, cli.require_packages)
RENDER_FILES = ("vesflow/render/", "vesflow/vtk_export.py")


def test_every_imported_package_is_declared():
    declared = _declared()
    table = md.packages_distributions()
    imported = _imported()
    assert {"numpy", "scipy", "h5py", "petsc4py", "mpi4py", "finufft", "ducc0", "pyvista"} <= set(imported)
    problems = []
    for module, files in sorted(imported.items()):
        if module == "tomli":           # Python < 3.11 only (scene/parser.py), declared with that marker
            assert any(r.startswith("tomli") and "python_version" in r
                       for r in tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"])
            continue
        dists = [_norm(d) for d in _dists_of(module, table)]
        if not dists:
            problems.append(f"{module} (imported by {files[0]}) is not installed: no distribution provides it")
            continue
        where = [declared[d] for d in dists if d in declared]
        if not where:
            problems.append(f"{module} ({'/'.join(dists)}, imported by {files[0]}) is not declared in pyproject.toml")
            continue
        render_only = all(f.startswith(RENDER_FILES) for f in files)
        need = OPTIONAL.get(module, "render" if render_only else "core")
        if need not in where and "core" not in where:
            problems.append(f"{module} is imported by {files[0]} but declared in {where}, not in {need}")
    assert not problems, "\n".join(problems)


def test_render_without_the_render_extra_names_the_missing_package(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)     # import fails as if not installed
    rc = cli.main(["render", str(tmp_path / "run.h5")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1
    assert "vesflow render needs the Python package imageio-ffmpeg" in err and "vesflow[render]" in err
    monkeypatch.setitem(sys.modules, "pyvista", None)
    assert cli.main(["render", str(tmp_path / "run.h5")]) == 2
    assert "packages pyvista, imageio-ffmpeg" in capsys.readouterr().err


def run(cmd, cwd, **kw):
    r = subprocess.run([str(c) for c in cmd], cwd=cwd, env=clean_env(), capture_output=True, text=True, **kw)
    assert r.returncode == 0, f"{' '.join(map(str, cmd))}: exit {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    return r.stdout


@pytest.fixture(scope="module")
def wheel_venv(tmp_path_factory):
    """The wheel built from the tree, installed into a fresh venv layered on the shared environment."""
    tmp = tmp_path_factory.mktemp("wheel")
    run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", ROOT, "-w", tmp / "dist"],
        cwd=ROOT)
    wheel, = (tmp / "dist").glob("vesflow-*.whl")
    venv = tmp / "venv"
    run([ROOT / "tools" / "layered_venv.sh", venv, shared_env()], cwd=tmp)
    run([venv / "bin" / "python", "-m", "pip", "install", "-q", "--no-deps", "--no-index", wheel], cwd=tmp)
    return venv


def test_wheel_in_a_fresh_venv_runs_check_run_render_and_export(wheel_venv, tmp_path):
    py, vesflow = wheel_venv / "bin" / "python", wheel_venv / "bin" / "vesflow"
    work = tmp_path / "elsewhere"
    work.mkdir()
    shutil.copy(ROOT / "runs" / "shear_pair.toml", work / "pair.toml")
    site = run([py, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"], cwd=work).strip()
    where = run([py, "-c", "import vesflow, vesflow.render, vesflow._kernels.stokes as k; "
                 "print(vesflow.__file__); print(k.__file__)"], cwd=work).split()
    assert all(w.startswith(site + "/vesflow/") for w in where), where    # the wheel's copy, not a tree
    # every requirement of the installed wheel (core and render extra) is installed
    missing = run([py, "-c", """
import importlib.metadata as md, re
bad = []
for r in md.requires("vesflow"):
    name, _, marker = r.partition(";")
    if "extra" in marker and "render" not in marker or "python_version" in marker:
        continue
    name = re.match(r"[A-Za-z0-9_.-]+", name).group(0)
    try:
        md.version(name)
    except md.PackageNotFoundError:
        bad.append(name)
print(" ".join(bad))
"""], cwd=work)
    assert missing.strip() == ""
    out = run([vesflow, "check", "pair.toml", "-ves_p", "4"], cwd=work)
    assert "memory" in out
    out = run([vesflow, "run", "pair.toml", "-o", "pair.h5", "-ves_p", "4", "-ts_max_time", "0.1",
               "-ves_output_every", "0.05"], cwd=work)
    assert "done at t = 0.1" in out
    run([vesflow, "render", "pair.h5", "-o", "pair.mp4"], cwd=work)
    assert (work / "pair.mp4").stat().st_size > 1000
    assert (work / "pair.xmf").is_file()                 # written by the run
    (work / "pair.xmf").unlink()
    assert run([vesflow, "export", "pair.h5"], cwd=work).strip().endswith("pair.xmf")
    assert "frames/points" in (work / "pair.xmf").read_text()

"""The tree's layout: `make bench` runs every script of benchmarks/, one-off studies are in
experiments/ with a README entry each, nothing edits sys.path to find vesflow, and tests share
code through tests/harness.py and tests/conftest.py only (no test module imports another)."""
import ast
import importlib.util
import re

from tests.harness import ROOT


def _run_all():
    spec = importlib.util.spec_from_file_location("run_all", ROOT / "benchmarks" / "run_all.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_make_bench_runs_every_benchmark():
    scripts = {p.name for p in (ROOT / "benchmarks").glob("*.py")} - {"run_all.py"}
    listed = [s for s, _, _ in _run_all().SCRIPTS]
    assert sorted(listed) == sorted(scripts) and len(listed) == len(set(listed))
    assert "run_all.py" in (ROOT / "Makefile").read_text()


def test_every_experiment_has_a_readme_entry_and_a_citation():
    readme = (ROOT / "experiments" / "README.md").read_text()
    rows = dict(re.findall(r"^\| `([a-z_0-9]+\.py)` \|.*\| ([^|]+) \|$", readme, re.M))
    scripts = {p.name for p in (ROOT / "experiments").glob("*.py")}
    assert set(rows) == scripts
    for script, cited in rows.items():             # each citing page names the script
        for page in (c.strip() for c in cited.split(",")):
            text = (ROOT / page).read_text()
            stem = script[:-3]
            assert f"experiments/{script}" in text or f"experiments.{stem}" in text, (script, page)


def _python_files():
    for sub in ("vesflow", "tests", "benchmarks", "experiments", "runs", "postprocess", "tools"):
        yield from (ROOT / sub).rglob("*.py")


def test_nothing_edits_sys_path():
    offenders = [str(p.relative_to(ROOT)) for p in _python_files()
                 if re.search(r"sys\.path\.(insert|append)", p.read_text())]
    assert offenders == []


def test_tests_import_no_other_test_module():
    bad = []
    for p in (ROOT / "tests").rglob("*.py"):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.ImportFrom):
                mods = [("." * node.level) + (node.module or "")] + [
                    f"{node.module}.{a.name}" if node.module else a.name for a in node.names]
            elif isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            else:
                continue
            if any(m.split(".")[-1].startswith("test_") or m.startswith(".") for m in mods):
                bad.append(f"{p.relative_to(ROOT)}: {mods[0]}")
    assert bad == []

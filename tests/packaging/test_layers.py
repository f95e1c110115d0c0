"""The package's layers import downwards only: scene -> surfaces -> state set-up -> forces ->
layer potentials -> operator -> solver -> stepping -> output -> entry points (LAYERS, below).

Every module of vesflow/ is parsed with `ast` (nothing is imported), its imports of the
package's own modules are collected, at module level and inside functions, and the test fails on
- a module that no layer of LAYERS holds (a new module must be placed),
- an import of a module of a higher layer (an upward import),
- a cycle of imports (any level, functions included; within a layer too),
- an import inside a function without a stated reason: a trailing `# lazy: <reason>` comment on
  the import's line (for a real reason only, e.g. numpy loaded after vesflow.threads has set the
  thread environment, an optional heavy dependency).
"""
from __future__ import annotations

import ast
import os
import re

import pytest

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..")
PACKAGE = "vesflow"

# Lowest first: a module may import modules of its own layer and of the layers before it.  A
# module belongs to the layer with the longest matching name (a package name covers its modules).
LAYERS = [
    ("base", ["vesflow", "vesflow.errors", "vesflow.calibration", "vesflow.options", "vesflow.timing",
              "vesflow.threads", "vesflow.parallel", "vesflow.signals", "vesflow._kernels"]),
    ("scene", ["vesflow.scene"]),
    ("surfaces", ["vesflow.sph", "vesflow.surface", "vesflow.shapes"]),
    ("state set-up", ["vesflow.setup_state"]),
    ("forces", ["vesflow.forces", "vesflow.flows", "vesflow.repulsion"]),
    ("layer potentials", ["vesflow.layerpot"]),
    ("operator", ["vesflow.operator"]),
    ("solver", ["vesflow.solver", "vesflow.precond", "vesflow.memory_model", "vesflow.costs"]),
    ("stepping", ["vesflow.stepping", "vesflow.stepper", "vesflow.sdc", "vesflow.simulation",
                  "vesflow.collision", "vesflow.contact", "vesflow.correction", "vesflow.reparam"]),
    ("output", ["vesflow.io", "vesflow.vtk_export"]),
    ("entry points", ["vesflow.cli", "vesflow.__main__", "vesflow.study", "vesflow.render", "vesflow.planner",
                      "vesflow.plan_fit", "vesflow.plan_command"]),
]
LAZY = re.compile(r"#\s*lazy:\s*\S")


def layer_of(module):
    """Index in LAYERS of a module name (None: no layer holds it)."""
    best, found = -1, None
    for k, (_, names) in enumerate(LAYERS):
        for n in names:
            if (module == n or (n != PACKAGE and module.startswith(n + "."))) and len(n) > best:
                best, found = len(n), k
    return found


def package_modules(root=ROOT):
    """{module name: path} of every .py file of the package."""
    out = {}
    for d, dirs, files in os.walk(os.path.join(root, PACKAGE)):
        dirs[:] = sorted(x for x in dirs if not x.startswith((".", "__pycache__")))
        for f in sorted(files):
            if f.endswith(".py"):
                path = os.path.join(d, f)
                name = os.path.relpath(path, root)[:-3].replace(os.sep, ".")
                out[name[:-len(".__init__")] if name.endswith(".__init__") else name] = path
    return out


def compiled_modules(root=ROOT):
    """Names of the compiled kernels (vesflow/_kernels/*.pyx): they import nothing of the package."""
    d = os.path.join(root, PACKAGE, "_kernels")
    return {f"{PACKAGE}._kernels.{f[:-4]}" for f in os.listdir(d) if f.endswith(".pyx")} if os.path.isdir(d) else set()


class Import:
    def __init__(self, source, target, line, in_function, reason):
        self.source, self.target, self.line, self.in_function, self.reason = source, target, line, in_function, reason

    def __repr__(self):
        return f"{self.source}:{self.line} -> {self.target}{' (in a function)' if self.in_function else ''}"


def imports_of(name, path, known):
    """The imports of package modules in one file (Import records).  `from . import x` is the
    module x when x is one, else the package; `from .m import f` is the module m."""
    with open(path, encoding="utf-8") as fh:
        text = fh.read()
    lines = text.splitlines()
    is_pkg = path.endswith("__init__.py")
    out = []

    def resolve(node):
        if isinstance(node, ast.Import):
            return [a.name for a in node.names if a.name == PACKAGE or a.name.startswith(PACKAGE + ".")]
        if node.level == 0:
            base = node.module or ""
            if not (base == PACKAGE or base.startswith(PACKAGE + ".")):
                return []
        else:
            parts = name.split(".") if is_pkg else name.split(".")[:-1]
            parts = parts[:len(parts) - (node.level - 1)]
            base = ".".join(parts + ([node.module] if node.module else []))
        return [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                end = getattr(child, "end_lineno", child.lineno)
                reason = any(LAZY.search(lines[k - 1]) for k in range(child.lineno, end + 1))
                for target in resolve(child):
                    out.append(Import(name, target, child.lineno, in_function, reason))
            visit(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    visit(ast.parse(text, filename=path), False)
    return out


def import_graph(root=ROOT):
    mods = package_modules(root)
    known = set(mods) | compiled_modules(root)
    edges = []
    for name, path in mods.items():
        edges += imports_of(name, path, known)
    return mods, known, edges


def find_cycle(nodes, edges):
    """One cycle of the directed graph as a list of nodes (first == last), or None."""
    succ = {n: sorted({e.target for e in edges if e.source == n and e.target != n}) for n in nodes}
    colour, stack = {n: 0 for n in nodes}, []

    def dfs(n):
        colour[n] = 1
        stack.append(n)
        for m in succ.get(n, ()):
            if colour.get(m, 2) == 1:
                return stack[stack.index(m):] + [m]
            if colour.get(m, 2) == 0:
                found = dfs(m)
                if found:
                    return found
        stack.pop()
        colour[n] = 2
        return None

    for n in sorted(nodes):
        if colour[n] == 0:
            found = dfs(n)
            if found:
                return found
    return None


def upward(edges):
    """The imports of a module of a higher layer."""
    return [e for e in edges if None not in (layer_of(e.source), layer_of(e.target))
            and layer_of(e.target) > layer_of(e.source)]


def bare(edges):
    """The imports inside functions without a stated reason."""
    return [e for e in edges if e.in_function and not e.reason]


@pytest.fixture(scope="module")
def graph():
    return import_graph()


def test_every_module_has_a_layer(graph):
    mods, known, _ = graph
    missing = sorted(m for m in known if layer_of(m) is None)
    assert not missing, f"modules in no layer (place them in tests/packaging/test_layers.py LAYERS): {missing}"


def test_imports_go_downwards(graph):
    _, _, edges = graph
    up = [f"{e!r}: {LAYERS[layer_of(e.source)][0]} imports {LAYERS[layer_of(e.target)][0]}" for e in upward(edges)]
    assert not up, "upward imports:\n" + "\n".join(up)


def test_no_import_cycle(graph):
    mods, known, edges = graph
    cycle = find_cycle(known, edges)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_function_level_imports_state_a_reason(graph):
    _, _, edges = graph
    found = [repr(e) for e in bare(edges)]
    assert not found, ("imports of the package's own modules inside functions without a `# lazy: <reason>` "
                       "comment (move them to the module's imports):\n" + "\n".join(found))


def test_the_checks_find_what_they_look_for(tmp_path):
    """The parser and the checks on a made-up package: a function-level import, a cycle, an
    upward import and a stated reason are each seen."""
    pkg = tmp_path / PACKAGE
    (pkg / "layerpot").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "layerpot" / "__init__.py").write_text("")
    (pkg / "errors.py").write_text("")
    (pkg / "sph.py").write_text("from . import errors\n\ndef f():\n    from .layerpot import far\n")
    (pkg / "layerpot" / "far.py").write_text("from .. import sph\nfrom ..errors import X\n\n"
                                             "def g():\n    from ..io import writer  # lazy: a reason\n")
    (pkg / "cli.py").write_text("import vesflow.sph\n")
    mods, known, edges = import_graph(str(tmp_path))
    got = {(e.source, e.target, e.in_function, e.reason) for e in edges}
    assert got == {("vesflow.sph", "vesflow.errors", False, False),
                   ("vesflow.sph", "vesflow.layerpot.far", True, False),
                   ("vesflow.layerpot.far", "vesflow.sph", False, False),
                   ("vesflow.layerpot.far", "vesflow.errors", False, False),
                   ("vesflow.layerpot.far", "vesflow.io", True, True),
                   ("vesflow.cli", "vesflow.sph", False, False)}
    cycle = find_cycle(known, edges)
    assert cycle is not None and cycle[0] == cycle[-1] and set(cycle) == {"vesflow.sph", "vesflow.layerpot.far"}
    assert {(e.source, e.target) for e in upward(edges)} == {("vesflow.sph", "vesflow.layerpot.far"),
                                                           ("vesflow.layerpot.far", "vesflow.io")}
    assert [(e.source, e.line) for e in bare(edges)] == [("vesflow.sph", 4)]
    assert find_cycle(known, [e for e in edges if e.source != "vesflow.sph"]) is None
    assert layer_of("vesflow.layerpot.far") > layer_of("vesflow.sph") > layer_of("vesflow.errors")
    assert layer_of("vesflow.stepping.adaptor") == layer_of("vesflow.simulation")
    assert layer_of("vesflow.sphx") is None and layer_of("vesflow") == 0


def test_the_stated_reasons_hold():
    """The entry point's and vesflow.threads' imports inside functions keep numpy and the
    compiled kernels unloaded until main() has set the thread environment (vesflow.threads)."""
    import subprocess
    import sys
    code = ("import sys, vesflow.cli, vesflow.threads; "
            "print(sorted(m for m in ('numpy', 'vesflow._kernels.series') if m in sys.modules))")
    env = dict(os.environ, PYTHONPATH=os.path.abspath(ROOT))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr

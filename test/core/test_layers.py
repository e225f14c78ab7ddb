"""The package's layers, as a contract CI runs: each layer imports only the layers below it, no
import cycle anywhere, and at most twelve entries at the top of the package.

Read from the source (``ast``): every import counts, at module level or inside a function, in any
form (``import a.b``, ``from . import x``, ``from ..core.frames import Site``, and the module names
given to ``importlib.import_module`` / ``importlib.util.find_spec``) — a lazy import is still a
dependency, and the cycles this replaced all hid inside functions.  (import-linter would say the
same with a ``layers`` contract; it is not in the environment, this needs nothing.)  And every
import of the package, in it and in the tests, benchmarks, scripts and examples, names a module of
the tree: the ROS install tree's copy of the package would otherwise answer a path that moved.
"""
import ast

import pytest

import pysource
from pysource import PKG
NAME = "inclinometer_calib"
#: Bottom to top: a module may import its own layer and the ones before it, never one after it.
LAYERS = ("core", "detect", "io", "calibrate", "correct", "rig", "lab", "fleet", "nodes", "apps")


def _module(path) -> tuple:
    parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
    is_pkg = parts[-1] == "__init__"
    return ".".join(parts[:-1] if is_pkg else parts), is_pkg


def _imported(name: str, is_pkg: bool, tree, modules) -> list:
    """Every name of the package that ``name`` imports, absolute (``from .x import y``: ``pkg.x.y``
    when ``y`` is a module, else ``pkg.x``)."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_pkg else name.split(".")[:-1]
                base = ".".join(base[:len(base) - node.level + 1] + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            found += [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        elif (isinstance(node, ast.Call) and isinstance(node.func, (ast.Attribute, ast.Name))
              and getattr(node.func, "attr", getattr(node.func, "id", "")) in ("import_module", "find_spec")
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            found.append(node.args[0].value)
    return [t for t in found if t == NAME or t.startswith(NAME + ".")]


def _targets(name: str, is_pkg: bool, tree, modules) -> set:
    """The package's modules ``name`` imports (each import resolved to the deepest module that exists)."""
    out = set()
    for t in _imported(name, is_pkg, tree, modules):
        while t not in modules and "." in t:
            t = t.rsplit(".", 1)[0]
        if t != name and t != NAME and t in modules:
            out.add(t)
    return out


@pytest.fixture(scope="module")
def sources() -> dict:
    """(module, is a package) -> its parsed source, for every module of the tree."""
    return {_module(p): pysource.parse(p) for p in pysource.files()}


@pytest.fixture(scope="module")
def graph(sources) -> dict:
    """module -> the package's modules it imports (the generated msg/srv are not in the source tree)."""
    modules = {name for name, _ in sources}
    return {name: _targets(name, is_pkg, tree, modules) for (name, is_pkg), tree in sources.items()}


def _defined(tree) -> set:
    """The names a module's top level binds (assignments, definitions, imports)."""
    out = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            for t in (node.targets if isinstance(node, ast.Assign) else [node.target]):
                out |= {n.id for n in ast.walk(t) if isinstance(n, ast.Name)}
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            out |= {(a.asname or a.name).split(".")[0] for a in node.names}
    return out


def test_every_import_of_the_package_names_a_module_of_the_tree(sources):
    # the ROS install tree merges into the package (extend_path) and may hold an older copy of it:
    # an import of a path that moved would still work there, from the stale copy — in the package,
    # and in the tests, benchmarks, scripts and examples that import it
    trees = {name: tree for (name, _), tree in sources.items()}
    defined = {name: _defined(tree) for name, tree in trees.items()}
    generated = (NAME + ".msg", NAME + ".srv")
    users = {(str(p.relative_to(PKG.parent)), False): pysource.parse(p)
             for folder in ("test", "benchmarks", "scripts", "examples", "launch")
             for p in pysource.files(PKG.parent / folder)}
    stale = []
    for (name, is_pkg), tree in {**sources, **users}.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                wanted = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".") if is_pkg else name.split(".")[:-1]
                    base = ".".join(base[:len(base) - node.level + 1] + ([node.module] if node.module else []))
                else:
                    base = node.module or ""
                if not (base == NAME or base.startswith(NAME + ".")) or base.startswith(generated):
                    continue
                if base not in trees:
                    wanted = [base]
                else:   # a submodule, or a name the module defines
                    wanted = [f"{base}.{a.name}" for a in node.names
                              if f"{base}.{a.name}" not in trees and a.name not in defined[base]]
            else:
                continue
            stale += [f"{name}: {t}" for t in wanted
                      if (t == NAME or t.startswith(NAME + ".")) and t not in trees and not t.startswith(generated)]
    assert stale == [], stale


def _layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_the_top_of_the_package_has_at_most_twelve_entries_and_they_are_the_layers():
    entries = sorted(p.name for p in PKG.iterdir() if p.name != "__pycache__")
    assert len(entries) <= 12, entries
    assert entries == sorted(("__init__.py",) + LAYERS), entries


def test_every_module_is_in_a_layer(graph):
    assert sorted(m for m in graph if m != NAME and _layer(m) not in LAYERS) == []


def test_each_layer_imports_only_the_layers_below_it(graph):
    rank = {layer: i for i, layer in enumerate(LAYERS)}
    upward = sorted(f"{m} -> {t}" for m, ts in graph.items() if m != NAME for t in ts
                    if rank[_layer(t)] > rank[_layer(m)])
    assert upward == [], "imports of a higher layer:\n" + "\n".join(upward)


def test_no_import_cycle_even_through_imports_inside_functions(graph):
    # Tarjan's strongly connected components: a component of more than one module is a cycle
    index, low, stack, on, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert cycles == [], f"import cycles: {cycles}"


def test_the_contract_sees_an_import_inside_a_function_and_the_relative_forms():
    # the check itself: a lazy upward import and `from .. import x` are found (else the tests above
    # could pass on a package whose layering they cannot see)
    src = ("def f():\n    from ..apps import cli\n    from ..io.bag import open_bag\n"
           "    import inclinometer_calib.rig.witsml\n")
    modules = {"inclinometer_calib.core.frames", "inclinometer_calib.apps.cli", "inclinometer_calib.io.bag",
               "inclinometer_calib.rig.witsml", "inclinometer_calib.apps", "inclinometer_calib.io"}
    got = _targets("inclinometer_calib.core.frames", False, ast.parse(src), modules)
    assert got == {"inclinometer_calib.apps.cli", "inclinometer_calib.io.bag", "inclinometer_calib.rig.witsml"}

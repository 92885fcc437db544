"""The package import graph is acyclic and flows one way: service -> jobs -> engine (docs/design.md §1).

Walks every module of engine/, jobs/, service/ (and bench/, for resolving names) with ``ast``: module-level
and function-level imports count alike, relative imports are resolved, and ``importlib.import_module`` /
``__import__`` with a literal (or an f-string's literal head) count too. Importing ``a.b.c`` is an edge to
``a.b.c`` only (not to the parent packages, as pydeps and importlab do); ``from a.b import c`` is an edge
to ``a.b.c`` when that is a module, else to ``a.b``.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CHECKED = ("engine", "jobs", "service")
PACKAGES = CHECKED + ("bench",)
#: importer -> packages it must never import
FORBIDDEN = {"engine": ("jobs", "service", "bench"), "jobs": ("service", "bench")}


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = path
    return mods


def _dynamic_target(node: ast.Call):
    """The module named by importlib.import_module(...) / __import__(...) with a literal argument, or the
    literal head of an f-string argument ('bench.{x}' -> 'bench'); None otherwise."""
    f = node.func
    name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
    if name not in ("import_module", "__import__") or not node.args:
        return None
    arg = node.args[0]
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value
    if isinstance(arg, ast.JoinedStr) and arg.values and isinstance(arg.values[0], ast.Constant):
        head = arg.values[0].value.rsplit(".", 1)[0] if "." in arg.values[0].value else ""
        return head or None
    return None


def imports_of(source: str, package: str, mods) -> set[str]:
    """Every module a source imports, anywhere in it; ``package``: the package it lives in (for relative
    imports), ``mods``: the known module names (``from a import b`` is ``a.b`` when that is one)."""
    targets: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            targets.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                src = ".".join(base + ([node.module] if node.module else []))
            else:
                src = node.module
            for a in node.names:
                sub = f"{src}.{a.name}"
                targets.add(sub if sub in mods else src)
        elif isinstance(node, ast.Call):
            t = _dynamic_target(node)
            if t:
                targets.add(t)
    return targets


def import_graph() -> dict[str, set[str]]:
    """module -> set of imported modules (only names under PACKAGES)."""
    mods = _modules()
    graph: dict[str, set[str]] = {}
    for mod, path in mods.items():
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        targets = imports_of(path.read_text(), package, mods)
        graph[mod] = {t for t in targets if t.split(".")[0] in PACKAGES}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module, or a self-import (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
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
            if len(comp) > 1 or v in graph.get(v, ()):
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_cycle_finder_sees_cycles():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"e"}}
    assert sorted(cycles(g)) == [["a", "b", "c"], ["e"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_walker_sees_function_level_relative_and_dynamic_imports():
    g = import_graph()
    # function-level: service/cli.py imports the app inside cmd_serve
    assert "service.app" in g["service.cli"]
    # 'from engine.physics import x' style resolves to the submodule when x is one
    assert "engine.physics.contact" in g["engine.loops.cpu"]
    src = ("import importlib\n"
           "def f():\n"
           "    from . import base\n"
           "    from ..physics.contact import min_image\n"
           "    from .. import errors\n"
           "    importlib.import_module(f'bench.{x}')\n"
           "    __import__('jobs.store')\n")
    mods = {"engine.backends.base", "engine.physics.contact", "engine.errors"}
    assert imports_of(src, "engine.backends", mods) == {
        "importlib", "engine.backends.base", "engine.physics.contact", "engine.errors", "bench", "jobs.store"}


def test_no_import_cycle_in_engine_jobs_service():
    g = import_graph()
    inner = {m: {t for t in ts if t.split(".")[0] in CHECKED} for m, ts in g.items() if m.split(".")[0] in CHECKED}
    found = cycles(inner)
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_dependencies_flow_service_jobs_engine():
    g = import_graph()
    bad = sorted(f"{m} -> {t}" for m, ts in g.items() for t in ts
                 if t.split(".")[0] in FORBIDDEN.get(m.split(".")[0], ()))
    assert not bad, "imports against the flow service -> jobs -> engine: " + ", ".join(bad)


# ---- engine layers (engine/README.md) -----------------------------------------------------------------------
#
# top      engine (the public entry points), engine.cli, engine.driver (runs specs: simulate, ensemble, startup),
#          engine.validation (`demq validate`: runs the driver): may import anything below
# shapes   engine.shapes.<pkg>: a shape plug-in; builds on engine.loops, never imports engine.backends
# backends engine.backends: the interfaces, the factories and the ensembles; reaches a shape only through the
#          registry engine.shapes, never a shape package
# loops    engine.loops: the generic time loops a shape's classes subclass and call; imports neither a shape package
#          nor the registry engine.shapes (a shape passes its kernels in), and of engine.backends only the
#          interfaces (protocol) and the types (base)
# physics  engine.physics: single-source njit functions; imports no other engine layer
# beside   engine.setup (spec -> derived parameters -> start), engine.output (result files, writers),
#          engine.analysis (theory and the analysis of results), engine.neighbours (cell arithmetic),
#          engine.numba_support: none of them imports the top layer; output and analysis import no loop, backend
#          or shape; neighbours only physics and numba_support; numba_support no other engine module

TOP = ("engine.driver", "engine.validation", "engine.cli")
#: the engine.backends modules engine/loops/ may import: the interfaces and the types
LOOPS_MAY_IMPORT = ("engine.backends.base", "engine.backends.protocol")
#: engine modules physics may import besides itself
PHYSICS_MAY_IMPORT = ("engine.physics", "engine.numba_support")


def _in(module: str, *packages: str) -> bool:
    """``module`` is one of ``packages`` or below one of them."""
    return any(module == p or module.startswith(p + ".") for p in packages)


def _shape_package(module: str) -> bool:
    """engine.shapes.<pkg> or below (not the registry engine.shapes itself)."""
    return module.startswith("engine.shapes.")


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """The imports against the layer rules above, as 'importer -> imported (rule)'."""
    bad = []
    for mod, targets in graph.items():
        if not _in(mod, "engine"):
            continue
        for t in targets:
            if not _in(t, "engine") or t == mod:
                continue
            why = None
            if _in(t, *TOP) and not _in(mod, *TOP) and mod != "engine":
                why = "only the driver, engine.cli, engine.validation and engine/__init__ import the top layer"
            elif _in(mod, "engine.backends") and _shape_package(t):
                why = "a backend names a shape package: use the registry engine.shapes"
            elif _shape_package(mod) and _in(t, "engine.backends"):
                why = "a shape package imports a backend: use engine.loops"
            elif _in(mod, "engine.loops") and (_in(t, "engine.shapes")
                                               or (_in(t, "engine.backends") and t not in LOOPS_MAY_IMPORT)):
                why = (f"engine.loops imports a shape or the shape registry, or a backend beyond "
                       f"{', '.join(LOOPS_MAY_IMPORT)}")
            elif _in(mod, "engine.physics") and not _in(t, *PHYSICS_MAY_IMPORT):
                why = "engine.physics imports another engine layer"
            elif _in(mod, "engine.output", "engine.analysis") and _in(t, "engine.loops", "engine.backends",
                                                                       "engine.shapes"):
                why = "result files and analysis import no loop, backend or shape"
            elif _in(mod, "engine.neighbours") and not _in(t, "engine.neighbours", *PHYSICS_MAY_IMPORT):
                why = "engine.neighbours imports only physics and numba_support"
            elif _in(mod, "engine.numba_support") and not _in(t, "engine.numba_support"):
                why = "engine.numba_support imports no other engine module"
            if why:
                bad.append(f"{mod} -> {t} ({why})")
    return sorted(bad)


def test_layer_rule_sees_each_kind_of_violation():
    g = {"engine.backends.cuda": {"engine.shapes.sphere.device", "engine.shapes", "engine.loops.cuda_kernels"},
         "engine.shapes.sphere.cpu_backend": {"engine.backends.cpu", "engine.loops.cpu"},
         "engine.shapes.spheroid.host": {"engine.backends"},
         "engine.loops.cpu": {"engine.backends.protocol", "engine.backends.registry", "engine.physics.contact"},
         "engine.loops.cuda_loop": {"engine.shapes.sphere", "engine.shapes"},
         "engine.setup.scene": {"engine.driver.simulate", "engine.setup.params"},
         "engine.physics.contact": {"engine.setup.params", "engine.numba_support.jitcache"},
         "engine.output.h5md": {"engine.loops.system", "engine.errors"},
         "engine.neighbours.cells": {"engine.setup.scene"},
         "engine.numba_support.jitcache": {"engine.errors"},
         "engine.driver.simulate": {"engine.shapes", "engine.loops.cpu", "engine.validation.sonine"},
         "engine": {"engine.driver.simulate"}}
    bad = layer_violations(g)
    assert [b.split(" (")[0] for b in bad] == [
        "engine.backends.cuda -> engine.shapes.sphere.device", "engine.loops.cpu -> engine.backends.registry",
        "engine.loops.cuda_loop -> engine.shapes", "engine.loops.cuda_loop -> engine.shapes.sphere",
        "engine.neighbours.cells -> engine.setup.scene", "engine.numba_support.jitcache -> engine.errors",
        "engine.output.h5md -> engine.loops.system", "engine.physics.contact -> engine.setup.params",
        "engine.setup.scene -> engine.driver.simulate", "engine.shapes.sphere.cpu_backend -> engine.backends.cpu",
        "engine.shapes.spheroid.host -> engine.backends"]


def test_the_engine_keeps_its_layers():
    bad = layer_violations(import_graph())
    assert not bad, "imports across the engine layers: " + "; ".join(bad)


def test_engine_top_level_stays_small():
    """engine/ holds its entry points and the modules every layer shares; the rest lives in role subpackages."""
    top = sorted(p.name for p in (ROOT / "engine").glob("*.py"))
    assert len(top) <= 12, top

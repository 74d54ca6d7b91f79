"""The engine's layers (docs/architecture.md): no import circle among the project's modules,
function-local imports included, and every import points down the layers.

Imports are read from the source with ``ast`` (as ../shared/tools/import_cycles.py does), so
an import inside a function counts as much as one at the top of a module."""
from __future__ import annotations

import ast
import os

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

#: the layers, lowest first; a module may import its own layer and the ones before it
LAYERS = ["core", "blocks", "structure", "results", "run", "compiled", "analysis", "views",
          "sweeps", "cli"]
#: modules outside the layers: the package's lazy public names, the plugin aliases
OUTSIDE = {"fwdstep", "fwdstep.block", "fwdstep.registry", "fwdstep.errors"}


def project_modules() -> dict:
    """Dotted name -> file for fwdstep/ and blocks/ (installed as fwdstep.blocks)."""
    mods = {}
    for top, prefix in (("fwdstep", "fwdstep"), ("blocks", "fwdstep.blocks")):
        base = os.path.join(ROOT, top)
        for folder, _, files in os.walk(base):
            for f in files:
                if f.endswith(".py"):
                    rel = os.path.relpath(os.path.join(folder, f), base)[:-3].replace(os.sep, ".")
                    name = prefix if rel == "__init__" else f"{prefix}.{rel}".removesuffix(".__init__")
                    mods[name] = os.path.join(folder, f)
    return mods


def imports_of(name: str, path: str, mods: dict) -> set:
    package = name if path.endswith("__init__.py") else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(open(path, encoding="utf-8").read(), path)):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            targets = [f"{base}.{a.name}" for a in node.names] + [base]
        else:
            continue
        for target in targets:
            if target == "blocks" or target.startswith("blocks."):
                target = "fwdstep." + target
            while target and target not in mods:
                target = target.rpartition(".")[0]
            if target and target != name and not name.startswith(target + ".") \
                    and target != "fwdstep":
                found.add(target)
    return found


def layer(name: str) -> str | None:
    parts = name.split(".")
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in LAYERS) else None


def circles(graph: dict) -> list:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, on, stack, out = {}, {}, set(), [], []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
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
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_circle_counting_function_local_imports():
    mods = project_modules()
    graph = {m: imports_of(m, p, mods) for m, p in mods.items()}
    assert circles(graph) == []


def test_the_circle_finder_finds_a_circle():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_every_import_points_down_the_layers():
    mods = project_modules()
    upward = []
    for m, p in sorted(mods.items()):
        if m in OUTSIDE:
            continue
        mine = layer(m)
        assert mine in LAYERS, f"{m} is in no layer of docs/architecture.md"
        for target in imports_of(m, p, mods):
            theirs = layer(target)
            if target in OUTSIDE or theirs is None:
                upward.append(f"{m} imports {target} (outside the layers)")
            elif LAYERS.index(theirs) > LAYERS.index(mine):
                upward.append(f"{m} ({mine}) imports {target} ({theirs})")
    assert upward == []


def test_the_plugin_imports_are_the_core_modules():
    import fwdstep.block
    import fwdstep.core.block
    import fwdstep.core.errors
    import fwdstep.core.registry
    import fwdstep.errors
    import fwdstep.registry
    assert fwdstep.block is fwdstep.core.block
    assert fwdstep.registry is fwdstep.core.registry
    assert fwdstep.errors is fwdstep.core.errors
    from fwdstep.registry import register
    assert register is fwdstep.core.registry.register

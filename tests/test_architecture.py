"""The package's layers and the direction of its imports (issue 14), checked on the source.

Layers, lowest first (docs/conventions.md, "Layers"): a module may import its own layer and
the layers below it, never above, whether the import is at the top of the file or inside a
function. A module's layer is the folder it lives in (``gtsam_sphere/<layer>/``). The arrows
that still point up are listed in ``KNOWN_UPWARD`` (debt to remove): the test fails on any
new one, and on a listed one that has gone (so the list only shrinks).
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "gtsam_sphere"

FOLDERS: dict[str, int] = {
    "core": 0,  # numpy (and gtsam types) only, no I/O
    "io": 1,  # formats and files
    "estimation": 2,  # factors, solvers, initialisation, corrections, calibration runs, rigs
    "analysis": 3,  # evaluate, uncertainty, compare
    "apps": 4,  # report, export, undistort, detect
    "simulate": 4,  # the simulator (calibrates its oracle) ...
    "cli": 5,  # the command line: one module per subcommand
}
# ... whose lens models and scenes are plain numpy, usable from the core
SIMULATOR_CORE = {"simulate.lenses": 0, "simulate.scenes": 0}
TOP = {"__main__": 5, "": 5}  # the package's front door


def layer_of(name: str) -> int:
    """The layer of a module, from the folder it lives in."""
    if name in SIMULATOR_CORE:
        return SIMULATOR_CORE[name]
    if name in TOP:
        return TOP[name]
    return FOLDERS[name.split(".")[0]]


KNOWN_UPWARD: set[tuple[str, str]] = set()

KNOWN_CYCLES: list[set[str]] = []


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        name = ".".join(p for p in parts if p != "__init__")
        out[name] = path
    return out


def _imports(name: str, path: Path, modules) -> set[str]:
    """Package modules ``name`` imports (relative imports, anywhere in the file)."""
    package = name.split(".")[:-1] if path.name != "__init__.py" else name.split(".")
    package = [p for p in package if p]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.ImportFrom) or not node.level:
            continue
        base = package[: len(package) - (node.level - 1)] if node.level > 1 else package
        target = ".".join([*base, *([node.module] if node.module else [])])
        if target in modules:
            found.add(target)
        for alias in node.names:  # from . import x
            sub = ".".join(p for p in (target, alias.name) if p)
            if sub in modules:
                found.add(sub)
    return found


def test_every_module_lives_in_a_layer_folder():
    loose = [n for n in _modules() if n not in TOP and n.split(".")[0] not in FOLDERS]
    assert not loose, f"modules outside the layer folders: {loose}"


def test_imports_point_down():
    modules = _modules()
    upward = set()
    for name, path in modules.items():
        for target in _imports(name, path, modules):
            if layer_of(target) > layer_of(name):
                upward.add((name, target))
    assert upward - KNOWN_UPWARD == set(), f"new upward imports: {sorted(upward - KNOWN_UPWARD)}"
    gone = KNOWN_UPWARD - upward
    assert gone == set(), f"gone, remove from KNOWN_UPWARD: {sorted(gone)}"


def _cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(comp)

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_no_new_import_cycles():
    modules = _modules()
    graph = {n: _imports(n, p, modules) - {""} for n, p in modules.items()}
    cycles = _cycles(graph)
    new = [c for c in cycles if c not in KNOWN_CYCLES]
    assert not new, f"new import cycles: {new}"
    assert all(c in cycles for c in KNOWN_CYCLES), f"gone, update KNOWN_CYCLES: {cycles}"


def test_one_factor_engine():
    """The Jacobian hand-off to GTSAM and the robust whitening live in one engine (issue 14):
    ``estimation.engine``; the M-estimators themselves in ``core.robust``."""
    homes = {"estimation.engine", "core.robust"}
    for name, path in _modules().items():
        text = path.read_text()
        for word in ("JacobianVector", "whitening_scale"):
            assert name in homes or word not in text, f"{name} uses {word}: use the engine"

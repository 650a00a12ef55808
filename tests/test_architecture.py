"""The package's layers, read from the source: imports go only downward, never in a circle, and
no module reaches for another module's private names.

The layers, lowest first (a module may import its own layer and those below):

0. ``errors``, ``resources``, ``dynamixel.control_table`` (the motors' data sheets, which robot
   descriptions check against);
1. ``robots``: descriptions, parameters, the symbolic models, one adapter per robot;
2. ``control``: the four controllers and the registry of their gains;
3. ``kernels``: C code generation, kernel naming, the ctypes library;
4. ``sim``: scenarios, unit setups, the CasADi and C closed loops;
5. ``runtime``: the real-time loop, the supervisor, the backend interface, the sim backend;
6. ``dynamixel``: the bridge, the protocol, the emulator;
7. ``apps``: the command-line tools and reports; and the package's own ``__init__`` (the
   public facade), which nothing inside imports.

Every import counts: inside functions, and under ``if TYPE_CHECKING:`` too (an annotation that
names a higher layer is a dependency all the same; a lower layer describes what it needs with a
Protocol instead, as ``robots.adapter.ScenarioView`` does).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "cochlea"

#: Module-name prefixes and their layer; the longest matching prefix decides.
LAYERS = {
    "errors": 0, "resources": 0, "dynamixel.control_table": 0,
    "robots": 1,
    "control": 2,
    "kernels": 3,
    "sim": 4,
    "ident": 4,
    "runtime": 5,
    "dynamixel": 6,
    "apps": 7, "": 7,
}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


MODULES = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def layer(module: str) -> int:
    matches = [prefix for prefix in LAYERS
               if module == prefix or module.startswith(prefix + ".") or prefix == ""]
    return LAYERS[max(matches, key=len)]


def imports(module: str) -> list[tuple[str, str | None, int]]:
    """``(imported cochlea module, name imported from it or None, line)`` of one module."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == "cochlea" or alias.name.startswith("cochlea."):
                    found.append((alias.name.removeprefix("cochlea").lstrip("."), None,
                                  node.lineno))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".") if package else []
                base = base[:len(base) - (node.level - 1)] if node.level > 1 else base
                target = ".".join(base + ([node.module] if node.module else []))
            elif node.module and (node.module == "cochlea" or node.module.startswith("cochlea.")):
                target = node.module.removeprefix("cochlea").lstrip(".")
            else:
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}" if target else alias.name
                if sub in MODULES:  # ``from package import module``
                    found.append((sub, None, node.lineno))
                else:
                    found.append((target, alias.name, node.lineno))
    return found


GRAPH = {m: imports(m) for m in MODULES}


def test_every_module_has_a_layer_and_every_import_resolves():
    for module, edges in GRAPH.items():
        for target, _, line in edges:
            assert target in MODULES, f"cochlea.{module}:{line} imports cochlea.{target}, " \
                                      "which is not a module of the package"


def test_imports_go_only_downward():
    upward = [f"cochlea.{m}:{line} (layer {layer(m)}) imports cochlea.{t} (layer {layer(t)})"
              for m, edges in GRAPH.items() for t, _, line in edges if layer(t) > layer(m)]
    assert not upward, "imports against the layer order:\n" + "\n".join(upward)


def test_nothing_inside_imports_the_package_facade():
    facade = [f"cochlea.{m}:{line}" for m, edges in GRAPH.items() for t, _, line in edges
              if t == ""]
    assert not facade, "modules importing cochlea/__init__.py:\n" + "\n".join(facade)


def test_no_import_cycle():
    edges = {m: sorted({t for t, _, _ in GRAPH[m] if t != m}) for m in GRAPH}
    state: dict[str, int] = {}  # 1: on the path, 2: done
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for t in edges[m]:
            if state.get(t) == 1:
                return path[path.index(t):] + [t]
            if t not in state and (cycle := visit(t)):
                return cycle
        path.pop()
        state[m] = 2
        return None

    for m in sorted(edges):
        if m not in state and (cycle := visit(m)):
            pytest.fail("import cycle: " + " -> ".join(f"cochlea.{c}" for c in cycle))


def test_no_private_name_crosses_a_module():
    private = [f"cochlea.{m}:{line} imports {name} from cochlea.{t}"
               for m, edges in GRAPH.items() for t, name, line in edges
               if name and name.startswith("_") and t != m]
    assert not private, "private names used across modules:\n" + "\n".join(private)


@pytest.mark.parametrize("bad, message", [
    ({"robots.x": [("sim.setup", None, 1)]}, "layer"),
    ({"robots.x": [("robots.y", None, 1)], "robots.y": [("robots.x", None, 2)]}, "cycle"),
    ({"sim.x": [("robots.y", "_hidden", 3)]}, "private"),
])
def test_the_checks_catch_what_they_are_for(monkeypatch, bad, message):
    """Each rule fails on a graph that breaks it (so a green run means something)."""
    for module in bad:
        monkeypatch.setitem(MODULES, module, PACKAGE / "x.py")
    monkeypatch.setattr(sys.modules[__name__], "GRAPH", {**GRAPH, **bad})
    checks = {"layer": test_imports_go_only_downward, "cycle": test_no_import_cycle,
              "private": test_no_private_name_crosses_a_module}
    with pytest.raises((AssertionError, pytest.fail.Exception)):
        checks[message]()

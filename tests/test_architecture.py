"""The package's layers, read from the source: imports go only downward, never in a circle, and
no module reaches for another module's private names.

The layers, lowest first (a module may import its own layer and those below):

0. ``errors``, ``resources``, ``dynamixel.control_table`` (the motors' data sheets, which robot
   descriptions check against), ``log_schema`` (the names of every log's columns, which the
   runtime, the embedded tables and the readers share), ``files`` (output paths checked and
   files written whole, for every tool), ``text`` (numbers read strictly, TOML strings and
   comments written escaped), ``sx_graph`` (CasADi expression graphs walked and rebuilt);
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
import functools
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "cochlea"

#: Module-name prefixes and their layer; the longest matching prefix decides.
LAYERS = {
    "errors": 0, "resources": 0, "console": 0, "dynamixel.control_table": 0, "log_schema": 0,
    "files": 0, "text": 0, "sx_graph": 0,
    "robots": 1,
    "control": 2,
    "kernels": 3,
    "sim": 4,
    "ident": 4,
    "runtime": 5,
    "dynamixel": 6,
    "sweep": 5,
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


@functools.cache
def graph() -> dict[str, list[tuple[str, str | None, int]]]:
    """Every module's :func:`imports`: parsed when a test first asks (not at collection, which
    every ``pytest -n`` worker pays), once per process."""
    return {m: imports(m) for m in MODULES}


def test_every_module_has_a_layer_and_every_import_resolves():
    for module, edges in graph().items():
        for target, _, line in edges:
            assert target in MODULES, f"cochlea.{module}:{line} imports cochlea.{target}, " \
                                      "which is not a module of the package"


def test_imports_go_only_downward():
    upward = [f"cochlea.{m}:{line} (layer {layer(m)}) imports cochlea.{t} (layer {layer(t)})"
              for m, edges in graph().items() for t, _, line in edges if layer(t) > layer(m)]
    assert not upward, "imports against the layer order:\n" + "\n".join(upward)


def test_nothing_inside_imports_the_package_facade():
    facade = [f"cochlea.{m}:{line}" for m, edges in graph().items() for t, _, line in edges
              if t == ""]
    assert not facade, "modules importing cochlea/__init__.py:\n" + "\n".join(facade)


def test_no_import_cycle():
    edges = {m: sorted({t for t, _, _ in out if t != m}) for m, out in graph().items()}
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
               for m, edges in graph().items() for t, name, line in edges
               if name and name.startswith("_") and t != m]
    assert not private, "private names used across modules:\n" + "\n".join(private)


@pytest.mark.parametrize("bad, message", [
    ({"robots.x": [("sim.setup", None, 1)]}, "layer"),
    ({"robots.x": [("robots.y", None, 1)], "robots.y": [("robots.x", None, 2)]}, "cycle"),
    ({"sim.x": [("robots.y", "_hidden", 3)]}, "private"),
])
def test_the_checks_catch_what_they_are_for(monkeypatch, bad, message):
    """Each rule fails on a graph that breaks it (so a green run means something)."""
    patched = {**graph(), **bad}  # the package's graph first, from the modules as they are
    for module in bad:
        monkeypatch.setitem(MODULES, module, PACKAGE / "x.py")
    monkeypatch.setattr(sys.modules[__name__], "graph", lambda: patched)
    checks = {"layer": test_imports_go_only_downward, "cycle": test_no_import_cycle,
              "private": test_no_private_name_crosses_a_module}
    with pytest.raises((AssertionError, pytest.fail.Exception)):
        checks[message]()


# ---- One place knows a robot (issue 25, item 6) ------------------------------------------------
#
# Everything specific to a kind of robot lives in cochlea/robots/<kind>/ and is reached through
# its adapter (cochlea.robots.robot(name), cochlea/robots/adapter.py; docs/extending.md).
# Outside cochlea/robots/ no module compares a value with a shipped robot's name, kind, arm or
# unit, keys a table by one, or imports cochlea.robots.serial / cochlea.robots.parallel.

ROBOTS_DATA = PACKAGE.parent / "models" / "robots"


def robot_names() -> set[str]:
    """The names that identify a shipped robot: each description's system name and kind and
    its arms' names (models/robots/*.toml), and the units the registry's adapters name
    ("mechanism")."""
    import tomllib

    from cochlea.robots import ROBOTS

    names = set(ROBOTS)
    for path in sorted(ROBOTS_DATA.glob("*.toml")):
        data = tomllib.loads(path.read_text())
        names |= {data["system"]["name"], data["system"].get("kind", data["system"]["name"])}
        names |= {arm["name"] for arm in data.get("arm", [])}
    for adapter in ROBOTS.values():
        names |= set(adapter.layout(adapter.load(None), "joint").units)
    return names


#: Where a robot's name may still appear outside cochlea/robots/, each with its reason:
#: ``(module, line's text fragment)`` for a name, ``(module, imported module)`` for an import.
#: Keep it short: a new entry needs a reason that is not about robot identity.
ALLOWED_NAMES: dict[tuple[str, str], str] = {}
ALLOWED_IMPORTS: dict[tuple[str, str], str] = {
    # The package's public facade (cochlea/__init__.py) has exported ``cochlea.load_serial``
    # since 0.1.0: a re-export for users, not a decision about a robot.
    ("", "robots.serial"): "public API: cochlea.load_serial",
}
KIND_PACKAGES = ("robots.serial", "robots.parallel")


def _strings(node: ast.AST, names: set[str]) -> list[str]:
    return [n.value for n in ast.walk(node) if isinstance(n, ast.Constant)
            and isinstance(n.value, str) and n.value in names]


def name_uses(tree: ast.AST, names: set[str]) -> list[tuple[int, str, str]]:
    """``(line, what, name)`` of each comparison (==, !=, in, is, match/case) with a string
    naming a robot, and of each table keyed or indexed by one, in ``tree``."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            found += [(node.lineno, "comparison", s) for s in _strings(node, names)]
        elif isinstance(node, ast.match_case):
            found += [(node.pattern.lineno, "case", s) for s in _strings(node.pattern, names)]
        elif isinstance(node, ast.Dict):
            found += [(k.lineno, "table key", s) for k in node.keys if k is not None
                      for s in _strings(k, names) if isinstance(k, ast.Constant)]
        elif isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant):
            found += [(node.lineno, "index", s) for s in _strings(node.slice, names)]
    return found


def robot_name_uses(package: Path = PACKAGE) -> list[str]:
    """Every use of a robot's name outside ``package/robots/`` not in :data:`ALLOWED_NAMES`."""
    names = robot_names()
    bad = []
    for path in sorted(package.rglob("*.py")):
        relative = path.relative_to(package)
        if relative.parts[0] == "robots":
            continue
        module = ".".join(relative.with_suffix("").parts).removesuffix("__init__").rstrip(".")
        lines = path.read_text().splitlines()
        for line, what, name in name_uses(ast.parse(path.read_text(), str(path)), names):
            text = lines[line - 1]
            if any(m == module and fragment in text for m, fragment in ALLOWED_NAMES):
                continue
            bad.append(f"cochlea/{relative}:{line}: {what} with {name!r}: {text.strip()}")
    return bad


def robot_kind_imports(modules: dict | None = None) -> list[str]:
    """Every import of a robot kind's package outside cochlea/robots/ not in
    :data:`ALLOWED_IMPORTS`."""
    bad = []
    for module, edges in (graph() if modules is None else modules).items():
        if module == "robots" or module.startswith("robots."):
            continue
        for target, name, line in edges:
            full = f"{target}.{name}" if name else target
            for kind in KIND_PACKAGES:
                if (full == kind or full.startswith(kind + ".") or target == kind
                        or target.startswith(kind + ".")) \
                        and (module, kind) not in ALLOWED_IMPORTS:
                    bad.append(f"cochlea.{module}:{line} imports cochlea.{full}")
    return bad


@pytest.mark.slow
def test_no_robot_name_outside_the_robots_layer():
    bad = robot_name_uses()
    assert not bad, ("a robot's name compared or used as a key outside cochlea/robots/ (ask its "
                     "adapter instead, docs/extending.md):\n" + "\n".join(bad))


def test_no_robot_kind_imported_outside_the_robots_layer():
    bad = robot_kind_imports()
    assert not bad, ("a robot kind's internals imported outside cochlea/robots/ (ask its "
                     "adapter, cochlea.robots.robot(name), instead):\n" + "\n".join(bad))


def test_the_names_are_the_shipped_robots():
    assert {"serial", "parallel", "arm1", "arm2", "mechanism"} <= robot_names()


@pytest.mark.parametrize("source", [
    'if robot == "serial":\n    pass\n',
    'ok = args.robot != "parallel"\n',
    'ok = unit in ("arm1", "arm2")\n',
    'match robot:\n    case "parallel":\n        pass\n',
    'TABLE = {"serial": 1}\n',
    'x = TABLE["parallel"]\n',
])
def test_the_name_check_catches_what_it_is_for(source):
    """Each form of a name's use is found (so a green run means something)."""
    assert name_uses(ast.parse(source), robot_names())


def test_plain_uses_of_a_name_pass():
    assert not name_uses(ast.parse('robot("serial")\nprint("serial arms")\n'), robot_names())


@pytest.mark.parametrize("edge", [("robots.serial.chain", None, 1), ("robots.parallel", "X", 1),
                                  ("robots.serial", None, 1)])
def test_the_import_check_catches_what_it_is_for(edge):
    assert robot_kind_imports({"ident.excite": [edge]})
    assert not robot_kind_imports({"robots.x": [edge]})

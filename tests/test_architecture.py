"""The dependency rules of docs/architecture.md, checked on the source (every import, including
the ones inside functions):

* each package and subpackage may import only the project packages listed in ``ALLOWED``;
* host never imports firmware_model except the composition root of ``ilcrig sim``
  (host/experiment/inprocess.py) and the CLI's role dispatch (which hands a whole process over to
  the firmware);
* the plant's model modules use numpy, scipy, numba and the standard library only;
* no import circle between modules;
* the names the command line offers are the names the code knows.
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("plant", "firmware_model", "bus", "host")
#: a subpackage comes before the package it is in: the first one a module's name starts with is its unit
SUBPACKAGES = (
    "bus.cia301",
    "bus.transports.hub",
    "bus.transports",
    "host.planning",
    "host.learning",
    "host.nodes",
    "host.experiment",
    "host.analysis",
    "host.rig",
)

#: unit -> the other units it may import.  A unit is a subpackage, or the top-level modules of a
#: package (``bus``, ``host``), or ``plant.plant_node`` (the plant's CANopen node, which alone of plant/
#: speaks CAN).
ALLOWED: dict[str, set[str]] = {
    "plant": set(),
    "plant.plant_node": {"plant", "bus", "bus.cia301", "bus.transports"},
    "bus": set(),
    "bus.cia301": {"bus"},
    "bus.transports": {"bus", "bus.transports.hub"},
    "bus.transports.hub": {"bus", "bus.transports"},
    "firmware_model": {"bus", "bus.cia301"},
    "host.planning": {"bus", "plant"},
    "host.learning": {"bus", "plant", "host.planning"},
    "host.nodes": {"bus", "bus.cia301"},
    "host.experiment": {"bus", "bus.cia301", "plant", "host.planning", "host.learning", "host.nodes"},
    "host.analysis": {"bus", "plant", "host.planning", "host.learning", "host.experiment"},
    "host.rig": {"bus", "bus.cia301", "bus.transports", "bus.transports.hub", "host.nodes", "host.experiment", "host.analysis"},
    "host": {
        "bus",
        "bus.cia301",
        "bus.transports",
        "bus.transports.hub",
        "plant",
        "plant.plant_node",
        "host.planning",
        "host.learning",
        "host.nodes",
        "host.experiment",
        "host.analysis",
        "host.rig",
    },
}
#: modules allowed to import firmware_model beyond their unit's rule
FIRMWARE_IMPORTERS = {"host.experiment.inprocess", "host.cli"}


def unit_of(module: str) -> str:
    """The unit (see ``ALLOWED``) a dotted module name belongs to."""
    if module == "plant.plant_node":
        return module
    for sub in SUBPACKAGES:
        if module == sub or module.startswith(sub + "."):
            return sub
    return module.split(".")[0]


def project_modules() -> Iterator[tuple[str, Path]]:
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT).with_suffix("")
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            yield ".".join(parts), path


def imports_of(path: Path) -> set[str]:
    """Every absolute import of the file, anywhere in it (``from a import b`` gives ``a`` and
    ``a.b``; which of them is a module is for the caller to decide)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module)
            found |= {f"{node.module}.{a.name}" for a in node.names}
    return found


MODULES = dict(project_modules())


def project_imports(path: Path) -> set[str]:
    """The project modules a file imports (names that are not modules are dropped)."""
    return {m for m in imports_of(path) if m in MODULES}


def test_every_unit_has_a_rule() -> None:
    units = {unit_of(m) for m in MODULES}
    assert units == set(ALLOWED), f"units without a rule: {units - set(ALLOWED)}; stale rules: {set(ALLOWED) - units}"


@pytest.mark.parametrize("unit", sorted(ALLOWED))
def test_dependency_direction(unit: str) -> None:
    bad: dict[str, list[str]] = {}
    for mod, path in MODULES.items():
        if unit_of(mod) != unit:
            continue
        allowed = ALLOWED[unit] | {unit} | ({"firmware_model"} if mod in FIRMWARE_IMPORTERS else set())
        wrong = sorted(m for m in project_imports(path) if unit_of(m) not in allowed)
        if wrong:
            bad[mod] = wrong
    assert not bad, f"{unit} may import only {sorted(ALLOWED[unit])}: {bad}"


def test_plant_models_use_numeric_libraries_only() -> None:
    allowed = {"numpy", "scipy", "numba", "plant"} | set(sys.stdlib_module_names)
    extra = {}
    for mod, path in MODULES.items():
        if unit_of(mod) == "plant":
            roots = {m.split(".")[0] for m in imports_of(path)}
            if roots - allowed:
                extra[mod] = sorted(roots - allowed)
    assert not extra, extra


def test_no_import_circles() -> None:
    graph = {mod: project_imports(path) - {mod} for mod, path in MODULES.items()}
    # a package's __init__ is imported with each of its modules: count that edge too
    for mod in list(graph):
        parent = mod.rpartition(".")[0]
        if parent in graph:
            graph[mod].add(parent)
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                cycle = stack[stack.index(n) :] + [n]
                pytest.fail("import circle: " + " -> ".join(cycle))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_every_package_says_what_it_owns_and_may_import() -> None:
    missing = []
    for pkg in (*PACKAGES, *SUBPACKAGES):
        init = ROOT / Path(*pkg.split(".")) / "__init__.py"
        doc = (ast.get_docstring(ast.parse(init.read_text())) or "").lower()
        if "owns" not in doc or "import" not in doc:
            missing.append(pkg)
    assert not missing, f"__init__ docstring must say what the package owns and what it may import: {missing}"


def test_cli_names_match_the_code() -> None:
    from bus.plant_objects import DisturbanceKind
    from host.experiment import console
    from host.learning import gains, laws, names
    from plant.disturbance import KINDS

    assert set(names.GAIN_PRESET_NAMES) == set(gains.GAIN_PRESETS)
    assert set(names.LAWS) == set(laws.LAW_CLASSES) and names.DEFAULT_LAW in names.LAWS
    assert tuple(k.label for k in DisturbanceKind) == KINDS
    assert console._DISTURBANCE_HELP == ", ".join(KINDS)

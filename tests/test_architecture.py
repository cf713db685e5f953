"""The dependency rules of docs/architecture.md, checked on the source (every import, including
the ones inside functions):

* each package and subpackage may import only the project packages listed in ``ALLOWED`` (no
  exceptions per module: the two composition roots are units with rules of their own);
* host never imports firmware_model except its two composition roots, :mod:`host.sim` (the
  in-process experiment of ``ilcrig sim`` and the API) and :mod:`host.cli` (the role dispatch, which
  hands a whole process over to the firmware);
* the plant's model modules use numpy, scipy, numba and the standard library only;
* the public API ``ilcrig`` may import host, bus and plant (the firmware only through
  host/sim/, never directly), and nothing in firmware_model, bus, host or plant imports ``ilcrig``;
* no import circle between modules;
* the names the command line offers are the names the code knows.
"""

from __future__ import annotations

import ast
import re
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("plant", "firmware_model", "bus", "host", "ilcrig")
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
    "host.studies.paper",
    "host.studies",
    "host.sim",
    "host.cli",
)

#: what both entry points, the command line (host.cli) and the public API (ilcrig), stand on: the
#: bus, the plant and every host subpackage but the command line and the paper's study
_BELOW_THE_ENTRY_POINTS: set[str] = {
    "bus",
    "bus.cia301",
    "bus.transports",
    "plant",
    *(sub for sub in SUBPACKAGES if sub.startswith("host.") and sub not in ("host.cli", "host.studies.paper")),
}

#: unit -> the other units it may import.  A unit is a subpackage, or the top-level modules of a
#: package (``bus``, ``host``), or ``plant.plant_node`` (the plant's CANopen node, which alone of plant/
#: speaks CAN: plant/plant_node.py and its parts plant/plant_node_*.py).
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
    # the studies of many experiments (the generic engine) and the paper's study on it
    "host.studies": {"bus", "plant", "host.planning", "host.learning", "host.experiment", "host.analysis", "host.sim"},
    "host.studies.paper": {"bus", "plant", "host.planning", "host.learning", "host.experiment", "host.analysis", "host.studies"},
    # composition root of the in-process experiment (ilcrig sim, the API): the firmware in this process
    "host.sim": {
        "bus",
        "bus.cia301",
        "plant",
        "firmware_model",
        "host.planning",
        "host.learning",
        "host.nodes",
        "host.experiment",
        "host.analysis",
    },
    # the command line: every role's process, the drive's included (firmware_model)
    "host.cli": {
        "bus.transports.hub",
        "plant.plant_node",
        "firmware_model",
        "host.studies.paper",
        *_BELOW_THE_ENTRY_POINTS,
    },
    "host": set(),
    "ilcrig": set(_BELOW_THE_ENTRY_POINTS),
}


def unit_of(module: str) -> str:
    """The unit (see ``ALLOWED``) a dotted module name belongs to."""
    if module == "plant.plant_node" or module.startswith("plant.plant_node_"):
        return "plant.plant_node"
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
        allowed = ALLOWED[unit] | {unit}
        wrong = sorted(m for m in project_imports(path) if unit_of(m) not in allowed)
        if wrong:
            bad[mod] = wrong
    assert not bad, f"{unit} may import only {sorted(ALLOWED[unit])}: {bad}"


def test_nothing_below_the_public_api_imports_it() -> None:
    importers = sorted(
        mod
        for mod, path in MODULES.items()
        if unit_of(mod).split(".")[0] != "ilcrig" and any(unit_of(m).split(".")[0] == "ilcrig" for m in project_imports(path))
    )
    assert importers == [], importers


def test_only_the_composition_roots_import_the_firmware() -> None:
    importers = {
        unit_of(mod)
        for mod, path in MODULES.items()
        if unit_of(mod).startswith("host") and any(unit_of(m) == "firmware_model" for m in project_imports(path))
    }
    assert importers <= {"host.sim", "host.cli"}, importers


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
    # a package's __init__ is imported with each of its modules: count that edge too, unless the
    # __init__ imports the module itself (a facade re-exporting it, as ilcrig's: importing the module
    # runs the __init__, which imports the module whole first — no partial import either way)
    explicit = {mod: set(edges) for mod, edges in graph.items()}
    for mod in list(graph):
        parent = mod.rpartition(".")[0]
        if parent in graph and mod not in explicit[parent]:
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
    from host.learning import gains, names
    from host.learning.laws.table import PROJECT_LAWS
    from plant.disturbance import KINDS

    assert set(names.GAIN_PRESET_NAMES) == set(gains.GAIN_PRESETS)
    assert tuple(PROJECT_LAWS) == names.PROJECT_LAW_NAMES and names.DEFAULT_LAW in names.LAWS
    assert set(names.LAWS) < set(names.PROJECT_LAW_NAMES) and {"cno-ilc", "adjoint-ilc"} <= set(names.PROJECT_LAW_NAMES)
    from host.learning.registry import law_names

    assert law_names()[: len(names.PROJECT_LAW_NAMES)] == names.PROJECT_LAW_NAMES
    assert tuple(k.label for k in DisturbanceKind) == KINDS
    assert console._DISTURBANCE_HELP == ", ".join(KINDS)


def test_cli_docstring_names_every_subcommand() -> None:
    import argparse

    from host import cli

    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    absent = [name for name in sub.choices if f"``{name}``" not in (cli.__doc__ or "")]
    assert not absent, f"host/cli/__init__.py's docstring does not name: {absent}"


def _layout_section() -> str:
    """§2 (Layout) of docs/architecture.md."""
    doc = (ROOT / "docs" / "architecture.md").read_text()
    start = doc.index("## 2. Layout")
    end = doc.index("\n## ", start + 1)
    return doc[start:end]


def _package_dirs() -> list[Path]:
    return sorted({p.parent for pkg in PACKAGES for p in (ROOT / pkg).rglob("__init__.py")})


def test_architecture_doc_names_every_module_of_the_tree() -> None:
    layout = _layout_section()
    missing = []
    for d in _package_dirs():
        for path in sorted(d.glob("*.py")):
            if path.name != "__init__.py" and path.name not in layout:
                missing.append(str(path.relative_to(ROOT)))
        for sub in sorted(p for p in d.iterdir() if (p / "__init__.py").exists()):
            if f"{sub.name}/" not in layout:
                missing.append(str(sub.relative_to(ROOT)) + "/")
    assert not missing, f"docs/architecture.md §2 does not name: {missing}"


def test_each_package_docstring_names_every_module_and_subpackage() -> None:
    missing: dict[str, list[str]] = {}
    for d in _package_dirs():
        doc = ast.get_docstring(ast.parse((d / "__init__.py").read_text())) or ""
        names = [p.stem for p in sorted(d.glob("*.py")) if p.name != "__init__.py"]
        names += [p.name for p in sorted(d.iterdir()) if (p / "__init__.py").exists()]
        absent = [n for n in names if not re.search(rf"(?<![\w]){re.escape(n)}(?![\w])", doc)]
        if absent:
            missing[str(d.relative_to(ROOT))] = absent
    assert not missing, f"__init__ docstrings that do not name every module: {missing}"


#: the longest class allowed in the project's packages, lines (a longer one holds several concerns)
MAX_CLASS_LINES = 400


def test_no_class_is_longer_than_the_limit() -> None:
    long = []
    for top in ("firmware_model", "bus", "host", "plant", "ilcrig"):
        for path in sorted((ROOT / top).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ClassDef) and node.end_lineno is not None:
                    n = node.end_lineno - node.lineno + 1
                    if n > MAX_CLASS_LINES:
                        long.append(f"{path.relative_to(ROOT)}: {node.name} ({n} lines)")
    assert not long, long

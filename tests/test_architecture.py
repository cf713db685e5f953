"""The dependency rules of DESIGN.md, checked on the source: plant needs only numpy/scipy/numba;
firmware_model never imports host or plant; bus never imports firmware_model, host or plant;
host never imports firmware_model except the composition root host/compose.py and the CLI's
role dispatch (which hands a whole process over to the firmware)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("plant", "firmware_model", "bus", "host")


def imported_roots(path: Path) -> set[str]:
    roots: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
    return roots


def modules(package: str) -> list[Path]:
    return sorted((ROOT / package).glob("*.py"))


@pytest.mark.parametrize(("package", "forbidden", "allowed_files"), [
    ("plant", {"bus", "host", "firmware_model", "can", "canopen"}, set()),
    ("firmware_model", {"host", "plant"}, set()),
    ("bus", {"host", "plant", "firmware_model"}, set()),
    ("host", {"firmware_model"}, {"compose.py", "cli.py"}),
])
def test_dependency_direction(package: str, forbidden: set[str], allowed_files: set[str]) -> None:
    bad = {p.name: sorted(imported_roots(p) & forbidden) for p in modules(package)
           if p.name not in allowed_files and imported_roots(p) & forbidden}
    assert not bad, f"{package} imports {bad}"


def test_plant_third_party_is_numeric_only() -> None:
    allowed = {"numpy", "scipy", "numba", "plant", "__future__", "dataclasses", "math", "logging",
               "typing", "functools", "time", "argparse", "enum", "collections", "sys", "os", "statistics"}
    extra = {p.name: sorted(imported_roots(p) - allowed) for p in modules("plant") if imported_roots(p) - allowed}
    assert not extra, extra


def test_cli_names_match_the_laws_and_presets() -> None:
    from host import ilc, names

    assert names.LAWS == ilc.LAWS
    assert set(names.GAIN_PRESET_NAMES) == set(ilc.GAIN_PRESETS)

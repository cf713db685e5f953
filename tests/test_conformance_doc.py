"""docs/canopen-objects.md §5.1, the drive's conformance table, and §7.1, the plant node's, are true to
bus/drive.eds and bus/plant.eds and to the test suite: each names every object of its EDS and no
other, once each, and every test it names exists (a ``def test_...`` in that file)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from canopen.objectdictionary import import_od

from bus.objects import DRIVE_EDS_PATH
from bus.plant_objects import PLANT_EDS_PATH

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "canopen-objects.md"
_ROW = re.compile(r"^\| (0x[0-9A-F]{4}) \|")
_TEST = re.compile(r"(tests/[\w/]+\.py)::(test_\w+)")


def conformance_rows(section: str = "### 5.1 Conformance table") -> dict[int, str]:
    """Index → the row's text, from the section ``section`` to the next heading."""
    text = DOC.read_text()
    start = text.index(section)
    end = text.index("\n#", start + 1)
    rows: dict[int, str] = {}
    for line in text[start:end].splitlines():
        m = _ROW.match(line)
        if m:
            index = int(m.group(1), 16)
            assert index not in rows, f"0x{index:04X} twice in the conformance table"
            rows[index] = line
    return rows


def test_the_conformance_table_names_exactly_the_objects_of_the_eds() -> None:
    eds = {obj.index for obj in import_od(str(DRIVE_EDS_PATH), 1).values() if obj.index >= 0x1000}
    rows = conformance_rows()
    assert sorted(eds - rows.keys()) == [], "EDS objects missing from the table"
    assert sorted(rows.keys() - eds) == [], "table rows without an EDS object"


PLANT_SECTION = "### 7.1 Conformance table (the plant node)"


def test_the_plant_table_names_exactly_the_objects_of_its_eds() -> None:
    eds = {obj.index for obj in import_od(str(PLANT_EDS_PATH), 32).values() if obj.index >= 0x1000}
    rows = conformance_rows(PLANT_SECTION)
    assert sorted(eds - rows.keys()) == [], "EDS objects missing from the table"
    assert sorted(rows.keys() - eds) == [], "table rows without an EDS object"


def test_every_test_the_table_names_exists() -> None:
    defined: dict[str, set[str]] = {}
    for index, row in (conformance_rows() | {0x10000 + i: r for i, r in conformance_rows(PLANT_SECTION).items()}).items():
        named = _TEST.findall(row)
        assert named, f"0x{index:04X}: no test named"
        for file, test in named:
            if file not in defined:
                path = REPO / file
                assert path.exists(), f"0x{index:04X}: {file} does not exist"
                tree = ast.parse(path.read_text())
                defined[file] = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
            assert test in defined[file], f"0x{index:04X}: {file}::{test} does not exist"

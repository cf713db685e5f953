"""Tests of host.planning.paths: built-in paths, TOML path files, path resolution."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from host.planning.paths import BUILTIN_PATHS, PathError, PathSpec, load_path_file, resolve_path

EXAMPLE = Path(__file__).resolve().parents[1] / "host" / "planning" / "path_files" / "example.toml"

GOOD = """\
name = "test gate"
pick = [-0.1, 0.02, -0.66]
place = [0.1, 0.02, -0.64]
lift = 0.03
rotation_deg = -45
"""


def write(tmp_path: Path, text: str) -> Path:
    f = tmp_path / "p.toml"
    f.write_text(text)
    return f


def test_path1_is_the_gate_of_robot_md() -> None:
    p = BUILTIN_PATHS[1]
    assert p.pick_xyz == (-0.1525, 0.0, -0.650)
    assert p.place_xyz == (0.1525, 0.0, -0.650)
    assert p.lift_m == 0.025
    assert p.rotation_rad == pytest.approx(math.pi / 2)
    assert p.top_z_m == pytest.approx(-0.625)
    assert p.horizontal_length_m == pytest.approx(0.305)


def test_builtin_paths_are_four_distinct_305mm_gates() -> None:
    assert sorted(BUILTIN_PATHS) == [1, 2, 3, 4]
    directions = set()
    for k, p in BUILTIN_PATHS.items():
        assert p.name == f"path {k}"
        assert p.horizontal_length_m == pytest.approx(0.305, abs=1e-4)
        assert p.lift_m == pytest.approx(0.025)
        assert abs(p.rotation_rad) == pytest.approx(math.pi / 2)
        dx = p.place_xyz[0] - p.pick_xyz[0]
        dy = p.place_xyz[1] - p.pick_xyz[1]
        directions.add((round(dx, 4), round(dy, 4), p.pick_xyz[1], p.pick_xyz[2]))
    assert len(directions) == 4
    # path 4 sits at another height than the others
    assert BUILTIN_PATHS[4].pick_xyz[2] != BUILTIN_PATHS[1].pick_xyz[2]


def test_load_good_file(tmp_path: Path) -> None:
    p = load_path_file(write(tmp_path, GOOD))
    assert p == PathSpec("test gate", (-0.1, 0.02, -0.66), (0.1, 0.02, -0.64), 0.03, math.radians(-45))
    assert p.top_z_m == pytest.approx(-0.61)  # lift above the higher end point


def test_example_file_loads() -> None:
    p = load_path_file(EXAMPLE)
    assert p.rotation_rad == pytest.approx(math.radians(45.0))
    assert p.lift_m == pytest.approx(0.020)
    assert resolve_path(str(EXAMPLE)) == p


def test_unknown_key(tmp_path: Path) -> None:
    with pytest.raises(PathError, match=r"unknown key\(s\) 'speed'") as exc:
        load_path_file(write(tmp_path, GOOD + "speed = 3\n"))
    assert "\n" not in str(exc.value)


def test_missing_key(tmp_path: Path) -> None:
    text = "\n".join(line for line in GOOD.splitlines() if not line.startswith("lift"))
    with pytest.raises(PathError, match=r"missing key\(s\) 'lift'") as exc:
        load_path_file(write(tmp_path, text))
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize(
    ("line", "replacement", "message"),
    [
        ("pick = [-0.1, 0.02, -0.66]", 'pick = [-0.1, "a", -0.66]', "'pick' must be a list of 3 numbers"),
        ("pick = [-0.1, 0.02, -0.66]", "pick = [-0.1, 0.02]", "'pick' must be a list of 3 numbers"),
        ("place = [0.1, 0.02, -0.64]", "place = 0.1", "'place' must be a list of 3 numbers"),
        ("lift = 0.03", 'lift = "high"', "'lift' must be a number > 0"),
        ("lift = 0.03", "lift = -0.01", "'lift' must be a number > 0"),
        ("lift = 0.03", "lift = true", "'lift' must be a number > 0"),
        ("rotation_deg = -45", "rotation_deg = [90]", "'rotation_deg' must be a number"),
        ('name = "test gate"', "name = 3", "'name' must be a non-empty string"),
    ],
)
def test_wrong_type(tmp_path: Path, line: str, replacement: str, message: str) -> None:
    with pytest.raises(PathError, match=message) as exc:
        load_path_file(write(tmp_path, GOOD.replace(line, replacement)))
    assert "\n" not in str(exc.value)
    assert isinstance(exc.value, ValueError)


def test_bad_toml_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(PathError, match="invalid TOML") as exc:
        load_path_file(write(tmp_path, "name = [\n"))
    assert "\n" not in str(exc.value)
    with pytest.raises(PathError, match="cannot read"):
        load_path_file(tmp_path / "nope.toml")


@pytest.mark.parametrize("spec", [1, "1", " 2", 3, "4"])
def test_resolve_builtin(spec: int | str) -> None:
    assert resolve_path(spec) is BUILTIN_PATHS[int(spec)]


@pytest.mark.parametrize("spec", [0, 5, "7", "-1"])
def test_unknown_builtin_number(spec: int | str) -> None:
    with pytest.raises(PathError, match=r"unknown built-in path -?\d+ \(built-in paths: 1, 2, 3, 4\)"):
        resolve_path(spec)


def test_resolve_unknown_name(tmp_path: Path) -> None:
    with pytest.raises(PathError, match="not a built-in path .* and no such file"):
        resolve_path(str(tmp_path / "missing.toml"))
    assert resolve_path(write(tmp_path, GOOD)).name == "test gate"


def test_pathspec_validates() -> None:
    with pytest.raises(PathError, match="lift"):
        PathSpec("x", (0, 0, -0.6), (0.1, 0, -0.6), 0.0, 0.0)
    with pytest.raises(PathError, match="pick_xyz"):
        PathSpec("x", (0, 0), (0.1, 0, -0.6), 0.02, 0.0)  # type: ignore[arg-type]
    with pytest.raises(PathError, match="pick_xyz"):
        PathSpec("x", (0, float("nan"), -0.6), (0.1, 0, -0.6), 0.02, 0.0)

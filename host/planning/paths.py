"""Pick-and-place task paths: the :class:`PathSpec` record, the four built-in paths and the
TOML path-file reader.

A path is a gate ("Adept-type") pick-and-place move: lift from the pick point, traverse, and
lower onto the place point, while the tool turns by ``rotation_rad``.  Coordinates are the
task frame of ``docs/architecture.md`` / docs/robot-model.md §3.1: base frame, z up, (x, y, z) is the
lower-platform (TCP) point in m, θ the tool angle about z in rad.  The lift is measured from
the higher of the two end points: the top of the gate is ``max(pick_z, place_z) + lift_m``.

Built-in paths (the paper's Fig. 11 shows four paths in different places/directions; the
exact coordinates were not published, so 2–4 are proposed here, all 25 × 305 × 25 mm with a
90° tool turn, all checked for reach and torque with the nominal model):

====  =====================================  ==================================  =======
path  pick → place (m)                        z0 (m)                              θ
====  =====================================  ==================================  =======
1     (−0.1525, 0, z0) → (+0.1525, 0, z0)     −0.650 (docs/robot-model.md §6.1, the gate)    +90°
2     (0, −0.1525, z0) → (0, +0.1525, z0)     −0.650 (along y)                    +90°
3     (−0.1078, −0.1078) → (+0.1078, +0.1078) −0.650 (diagonal, 305 mm long)      +90°
4     (−0.1525, +0.08) → (+0.1525, +0.08)     −0.700 (offset in y, lower)         −90°
====  =====================================  ==================================  =======

Path file (TOML), all five keys required, no others::

    name = "my path"
    pick = [-0.15, 0.0, -0.65]     # m
    place = [0.15, 0.0, -0.65]     # m
    lift = 0.025                   # m, > 0
    rotation_deg = 90.0            # deg, tool turn on the outward journey
"""

from __future__ import annotations

import logging
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bus.errors import InputError

logger = logging.getLogger(__name__)

__all__ = [
    "PathError",
    "PathSpec",
    "BUILTIN_PATHS",
    "load_path_file",
    "resolve_path",
]

#: pick and place of a path file closer than this in every coordinate are the same point (refused), m
_SAME_POINT_M = 1e-6
#: Keys of a path file and what each must hold.
PATH_FILE_KEYS: tuple[str, ...] = ("name", "pick", "place", "lift", "rotation_deg")


class PathError(InputError):
    """A path specification, path number or path file is invalid (one-line message)."""


def _finite_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class PathSpec:
    """One pick-and-place path.

    :param name: human-readable name (used in messages and reports).
    :param pick_xyz: pick point (x, y, z) in m, z = lower-platform/TCP height.
    :param place_xyz: place point (x, y, z) in m.
    :param lift_m: gate height above the higher end point, m (> 0).
    :param rotation_rad: tool turn from pick to place, rad (the return journey turns back).
    """

    name: str
    pick_xyz: tuple[float, float, float]
    place_xyz: tuple[float, float, float]
    lift_m: float
    rotation_rad: float

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise PathError("path name must be a non-empty string")
        for label in ("pick_xyz", "place_xyz"):
            point = getattr(self, label)
            if len(point) != 3 or not all(_finite_number(c) for c in point):
                raise PathError(f"path {self.name!r}: {label} must be 3 finite numbers (m)")
            object.__setattr__(self, label, tuple(float(c) for c in point))
        if not _finite_number(self.lift_m) or self.lift_m <= 0.0:
            raise PathError(f"path {self.name!r}: lift must be a number > 0 m, got {self.lift_m!r}")
        if not _finite_number(self.rotation_rad):
            raise PathError(f"path {self.name!r}: rotation must be a finite number")
        object.__setattr__(self, "lift_m", float(self.lift_m))
        object.__setattr__(self, "rotation_rad", float(self.rotation_rad))

    @property
    def top_z_m(self) -> float:
        """Height of the top of the gate, m."""
        return max(self.pick_xyz[2], self.place_xyz[2]) + self.lift_m

    @property
    def horizontal_length_m(self) -> float:
        """Length of the horizontal run, m."""
        return math.hypot(self.place_xyz[0] - self.pick_xyz[0], self.place_xyz[1] - self.pick_xyz[1])

    def describe(self) -> str:
        """One line: name, end points (mm), lift (mm), rotation (deg)."""
        p = ", ".join(f"{1e3 * c:.1f}" for c in self.pick_xyz)
        q = ", ".join(f"{1e3 * c:.1f}" for c in self.place_xyz)
        return (
            f"{self.name}: pick ({p}) mm -> place ({q}) mm, lift {1e3 * self.lift_m:.1f} mm, "
            f"rotation {math.degrees(self.rotation_rad):+.1f} deg"
        )


_Z0 = -0.650  # m, pick/place height of the gate (docs/robot-model.md §6.1)
_HALF = 0.305 / 2.0  # m, half the 305 mm horizontal run
_DIAG = _HALF / math.sqrt(2.0)  # m, per-axis half run of the 45° diagonal path

BUILTIN_PATHS: dict[int, PathSpec] = {
    1: PathSpec("path 1", (-_HALF, 0.0, _Z0), (_HALF, 0.0, _Z0), 0.025, math.pi / 2),
    2: PathSpec("path 2", (0.0, -_HALF, _Z0), (0.0, _HALF, _Z0), 0.025, math.pi / 2),
    3: PathSpec("path 3", (-_DIAG, -_DIAG, _Z0), (_DIAG, _DIAG, _Z0), 0.025, math.pi / 2),
    4: PathSpec("path 4", (-_HALF, 0.08, -0.700), (_HALF, 0.08, -0.700), 0.025, -math.pi / 2),
}


def _point(file: str, key: str, value: Any) -> tuple[float, float, float]:
    if not isinstance(value, list) or len(value) != 3 or not all(_finite_number(c) for c in value):
        raise PathError(f"path file {file}: '{key}' must be a list of 3 numbers [x, y, z] in m")
    return (float(value[0]), float(value[1]), float(value[2]))


def load_path_file(path: str | Path) -> PathSpec:
    """Read a path from a TOML file (keys: name, pick, place, lift, rotation_deg).

    :raises PathError: unreadable file, TOML syntax error, unknown or missing key, wrong type.
    """
    file = str(path)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except OSError as exc:
        raise PathError(f"path file {file}: cannot read ({exc.strerror or exc})") from exc
    except tomllib.TOMLDecodeError as exc:
        raise PathError(f"path file {file}: invalid TOML ({exc})".replace("\n", " ")) from exc

    unknown = sorted(set(data) - set(PATH_FILE_KEYS))
    if unknown:
        raise PathError(
            f"path file {file}: unknown key(s) {', '.join(repr(k) for k in unknown)} (allowed: {', '.join(PATH_FILE_KEYS)})"
        )
    missing = [k for k in PATH_FILE_KEYS if k not in data]
    if missing:
        raise PathError(f"path file {file}: missing key(s) {', '.join(repr(k) for k in missing)}")

    name = data["name"]
    if not isinstance(name, str) or not name:
        raise PathError(f"path file {file}: 'name' must be a non-empty string")
    pick = _point(file, "pick", data["pick"])
    place = _point(file, "place", data["place"])
    lift = data["lift"]
    if not _finite_number(lift) or lift <= 0.0:
        raise PathError(f"path file {file}: 'lift' must be a number > 0 (m), got {lift!r}")
    rot = data["rotation_deg"]
    if not _finite_number(rot):
        raise PathError(f"path file {file}: 'rotation_deg' must be a number (deg), got {rot!r}")
    if all(abs(a - b) < _SAME_POINT_M for a, b in zip(pick, place)):
        # the planner can do it (a lift and back), but as a pick-and-place task it is a mistake
        raise PathError(f"path file {file}: pick and place are the same point: there is nothing to carry")
    spec = PathSpec(name, pick, place, float(lift), math.radians(float(rot)))
    logger.debug("loaded %s from %s", spec.describe(), file)
    return spec


def resolve_path(spec: str | int | Path) -> PathSpec:
    """Turn a CLI path argument into a :class:`PathSpec`.

    ``1``..``4`` (int or digit string) select a built-in path; anything else is a TOML file.

    :raises PathError: unknown built-in number, missing or invalid file.
    """
    known = ", ".join(str(k) for k in sorted(BUILTIN_PATHS))
    if isinstance(spec, bool):
        raise PathError(f"invalid path {spec!r} (built-in paths: {known}, or a .toml file)")
    if isinstance(spec, int):
        number = spec
    elif isinstance(spec, str) and spec.strip().lstrip("+-").isdigit():
        number = int(spec.strip())
    else:
        file = Path(spec)
        if not file.is_file():
            raise PathError(f"unknown path {str(spec)!r}: not a built-in path ({known}) and no such file")
        return load_path_file(file)
    if number not in BUILTIN_PATHS:
        raise PathError(f"unknown built-in path {number} (built-in paths: {known})")
    return BUILTIN_PATHS[number]

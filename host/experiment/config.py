"""Experiment configuration: one frozen dataclass, built from a TOML file and/or CLI options.

Precedence (one place, :func:`build_config`): command-line option > TOML file (``--config``) >
defaults below.  Unknown keys and bad values are :class:`ConfigError` (a ``ValueError``) with a
one-line message; the CLI turns them into exit code 2 before anything moves.

TOML layout::

    law = "no-ilc-id"       # see host.learning.names.LAWS (default DEFAULT_LAW)
    iterations = 10         # 1 .. host.learning.names.MAX_ITERATIONS
    path = "1"              # 1..4 or a path TOML file
    cycle_s = 0.25          # single-journey time, s
    profile = "ruckig"      # ruckig | poly4567 | poly5
    disturbance = "none"    # none | repetitive | nonrepetitive | both
    seed = 0
    ts_s = 0.001            # control period, s
    substeps = 4            # RK4 sub-steps per control period
    ff0 = "model"           # initial feed-forward: "model" (nominal inverse dynamics) | "zero"
    following_error_deg = 10.0
    ff_transport = "table"  # feed-forward by SDO tables ("table") or each tick by SYNC + PDOs ("pdo")
    fieldbus_bitrate = 1000000  # bit/s, for the bus-fit check of the pdo transport
    force_bus_fit = false   # run a pdo configuration even if it does not fit the fieldbus

    [gains]                 # host.learning.gains.GainSpec fields; preset = "normalized" | "paper"
    preset = "normalized"
    alpha = 3.0
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bus.busload import DEFAULT_BITRATE_BPS
from bus.cyclic import FF_TRANSPORTS, cyclic_bus_fit
from host.learning.gains import GAIN_PRESETS, GainSpec
from host.learning.names import DEFAULT_LAW, LAWS, MAX_ITERATIONS
from host.planning.trajectory import PROFILES
from plant.disturbance import KINDS as DISTURBANCES

__all__ = ["ConfigError", "ExperimentConfig", "build_config", "PROFILES", "DISTURBANCES"]



class ConfigError(ValueError):
    """A configuration value or key is not acceptable."""


@dataclass(frozen=True)
class ExperimentConfig:
    law: str = DEFAULT_LAW
    iterations: int = 10
    path: str = "1"
    cycle_s: float = 0.25
    profile: str = "ruckig"
    disturbance: str = "none"
    seed: int = 0
    ts_s: float = 0.001
    substeps: int = 4
    ff0: str = "model"
    following_error_deg: float = 10.0
    ff_transport: str = "table"
    fieldbus_bitrate: int = DEFAULT_BITRATE_BPS
    force_bus_fit: bool = False
    gains: GainSpec = field(default_factory=GainSpec)

    def as_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["gains"] = dataclasses.asdict(self.gains)
        return d


_TOP_KEYS = {f.name for f in dataclasses.fields(ExperimentConfig)}
_GAIN_KEYS = {f.name for f in dataclasses.fields(GainSpec)} - {"name"} | {"preset"}


def _check_number(name: str, v: Any, *, integer: bool = False) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (integer and not isinstance(v, int)):
        raise ConfigError(f"{name} must be {'an integer' if integer else 'a number'}, got {v!r}")
    if not math.isfinite(float(v)):
        raise ConfigError(f"{name} must be finite, got {v!r}")


def _gain_spec(table: Mapping[str, Any]) -> GainSpec:
    unknown = set(table) - _GAIN_KEYS
    if unknown:
        raise ConfigError(f"unknown key(s) in [gains]: {', '.join(sorted(unknown))}")
    preset = table.get("preset", "normalized")
    if preset not in GAIN_PRESETS:
        raise ConfigError(f"unknown gain preset {preset!r}; choose one of {', '.join(GAIN_PRESETS)}")
    base = GAIN_PRESETS[preset]
    changes: dict[str, Any] = {}
    for k, v in table.items():
        if k == "preset":
            continue
        if v is None:
            changes[k] = None
            continue
        _check_number(f"gains.{k}", v, integer=k in ("lead", "q_order"))
        changes[k] = v
    if changes:
        changes["name"] = f"{preset}+custom"
    return dataclasses.replace(base, **changes)


def build_config(toml_path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> ExperimentConfig:
    """Merge defaults < TOML file < ``overrides`` (CLI options that were given) and validate."""
    data: dict[str, Any] = {}
    if toml_path is not None:
        p = Path(toml_path)
        try:
            data = tomllib.loads(p.read_text())
        except FileNotFoundError:
            raise ConfigError(f"config file not found: {p}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"config file {p} is not valid TOML: {exc}") from None
    for k, v in (overrides or {}).items():
        if v is not None:
            data[k] = v
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise ConfigError(f"unknown key(s): {', '.join(sorted(unknown))}")
    gains_table = data.pop("gains", {})
    if isinstance(gains_table, GainSpec):
        spec = gains_table
    else:
        if not isinstance(gains_table, dict):
            raise ConfigError("gains must be a table")
        spec = _gain_spec(gains_table)
    if "path" in data:
        data["path"] = str(data["path"])
    cfg = ExperimentConfig(**data, gains=spec)
    validate(cfg)
    return cfg


def validate(cfg: ExperimentConfig) -> None:
    """Raise :class:`ConfigError` on any value that cannot run."""
    if cfg.law not in LAWS:
        raise ConfigError(f"unknown law {cfg.law!r}; choose one of {', '.join(LAWS)}")
    _check_number("iterations", cfg.iterations, integer=True)
    if not 1 <= cfg.iterations <= MAX_ITERATIONS:
        raise ConfigError(f"iterations must be between 1 and {MAX_ITERATIONS}, got {cfg.iterations}")
    _check_number("cycle_s", cfg.cycle_s)
    if cfg.cycle_s <= 0:
        raise ConfigError(f"cycle_s must be > 0, got {cfg.cycle_s}")
    if cfg.profile not in PROFILES:
        raise ConfigError(f"unknown profile {cfg.profile!r}; choose one of {', '.join(PROFILES)}")
    if cfg.disturbance not in DISTURBANCES:
        raise ConfigError(f"unknown disturbance {cfg.disturbance!r}; choose one of {', '.join(DISTURBANCES)}")
    _check_number("seed", cfg.seed, integer=True)
    if cfg.seed < 0:
        raise ConfigError(f"seed must be >= 0, got {cfg.seed}")
    _check_number("ts_s", cfg.ts_s)
    if not 1e-4 <= cfg.ts_s <= 1e-2:
        raise ConfigError(f"ts_s must be between 0.0001 and 0.01 s, got {cfg.ts_s}")
    _check_number("substeps", cfg.substeps, integer=True)
    if not 1 <= cfg.substeps <= 100:
        raise ConfigError(f"substeps must be between 1 and 100, got {cfg.substeps}")
    if cfg.ff0 not in ("model", "zero"):
        raise ConfigError(f"ff0 must be 'model' or 'zero', got {cfg.ff0!r}")
    _check_number("following_error_deg", cfg.following_error_deg)
    if cfg.following_error_deg <= 0:
        raise ConfigError(f"following_error_deg must be > 0, got {cfg.following_error_deg}")
    if cfg.ff_transport not in FF_TRANSPORTS:
        raise ConfigError(f"ff_transport must be one of {', '.join(FF_TRANSPORTS)}, got {cfg.ff_transport!r}")
    _check_number("fieldbus_bitrate", cfg.fieldbus_bitrate, integer=True)
    if cfg.fieldbus_bitrate <= 0:
        raise ConfigError(f"fieldbus_bitrate must be > 0 bit/s, got {cfg.fieldbus_bitrate}")
    if not isinstance(cfg.force_bus_fit, bool):
        raise ConfigError(f"force_bus_fit must be true or false, got {cfg.force_bus_fit!r}")
    if cfg.ff_transport == "pdo":
        fit = cyclic_bus_fit(cfg.ts_s, cfg.fieldbus_bitrate)
        if not fit.fits and not cfg.force_bus_fit:
            raise ConfigError(
                f"the cyclic PDO exchange does not fit the fieldbus: {fit.message()}; a real master would "
                "lower the control rate, map fewer objects or use several PDOs per drive at a lower rate "
                "(docs/timing.md §7); --force-bus-fit runs it anyway")
    g = cfg.gains
    for name in ("alpha", "beta", "lp_norm", "ld_norm", "q_cutoff_hz", "pdq_cutoff_hz", "no_weight", "lp", "ld"):
        v = getattr(g, name)
        if v is not None and (not math.isfinite(v)):
            raise ConfigError(f"gains.{name} must be finite, got {v}")
        if v is not None and v < 0:
            raise ConfigError(f"gains.{name} must be >= 0, got {v}")
    if g.alpha < 1 or g.beta < 1:
        raise ConfigError(f"gains.alpha and gains.beta must be >= 1, got {g.alpha}, {g.beta}")
    if g.lead < 0:
        raise ConfigError(f"gains.lead must be >= 0, got {g.lead}")
    nyquist_hz = 0.5 / cfg.ts_s
    for name in ("q_cutoff_hz", "pdq_cutoff_hz"):
        if not 0 < getattr(g, name) < nyquist_hz:
            raise ConfigError(f"gains.{name} must be between 0 and {nyquist_hz:g} Hz (Nyquist), got {getattr(g, name)}")
    if g.q_order < 1:
        raise ConfigError(f"gains.q_order must be >= 1, got {g.q_order}")
    if not g.no_weight > 0:
        raise ConfigError(f"gains.no_weight must be > 0, got {g.no_weight}")

"""Experiment configuration: one frozen dataclass, built from a TOML file and/or CLI options.

Precedence (one place, :func:`build_config`): command-line option > TOML file (``--config``) >
defaults below; the ``[gains]`` table merges key by key (a ``--lp`` on the command line keeps the
file's ``alpha``).  Unknown keys and bad values are :class:`ConfigError` (a ``ValueError``) with a
one-line message naming the key (and the file); the CLI turns them into exit code 2 before anything
moves.  Refused: an unreadable, binary or invalid TOML file; a key of the wrong type
(``gains = 5``, ``law = 3``); NaN or ±inf anywhere; values out of range, among them more than
:data:`MAX_ITERATIONS` trials and a seed outside the bench's 32 bits.  A relative ``path`` given
in the file is a path file relative to the file's folder (on the command line: to the working
directory).  The one writer of experiment files is here too: :func:`config_toml` (a configuration,
as ``ilcrig.RigRun`` hands it to ``ilcrig run``) and :func:`options_toml` (experiment options, as
``ilcrig tune`` writes its ``best.toml``).

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

    [law_options]           # the law's own options (names and meaning: the law's documentation)
    torque_limit_nm = 200.0

    [plant]                 # plant uncertainty: factors on the emulated robot (plant.params.PlantScales)
    inertia_scale = 1.0     # rotational inertias
    mass_scale = 1.0        # link and platform masses
    friction_scale = 1.0    # Coulomb and viscous friction
    payload_scale = 1.0     # the payload

``law`` is a built-in law, a plug-in's name (entry-point group ``ilcrig.laws``) or
``module:Class`` (:mod:`host.learning.registry`).  ``[law_options]`` values are numbers, strings
or booleans; the law checks them when it is built (:func:`host.experiment.plan.prepare`).
``[plant]`` changes the emulated robot only (the nominal model, the plan and the gains stay); with
every factor 1 it is left out of :meth:`ExperimentConfig.as_dict`, so summaries of the robot as
built are unchanged.
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
from bus.errors import InputError
from host.learning.gains import GAIN_PRESETS, GainSpec
from host.learning.names import DEFAULT_LAW, MAX_ITERATIONS
from host.learning.registry import check_law_name
from host.planning.task_plan import PROFILES
from plant.disturbance import KINDS as DISTURBANCES
from plant.params import PlantScales

__all__ = [
    "ConfigError",
    "ExperimentConfig",
    "build_config",
    "gains_table",
    "toml_value",
    "options_toml",
    "config_toml",
    "validate",
    "PROFILES",
    "DISTURBANCES",
    "MAX_ITERATIONS",
    "MAX_SEED",
    "PLANT_KEYS",
]

#: the largest seed (the plant node's 0x2400:4 is 32 bits)
MAX_SEED: int = 0xFFFFFFFF
_BUILTIN_PATH_NAMES = {"1", "2", "3", "4"}


class ConfigError(InputError):
    """A configuration value or key is not acceptable (bad input: exit code 2)."""


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
    law_options: dict[str, Any] = field(default_factory=dict)
    plant: PlantScales = field(default_factory=PlantScales)

    @property
    def n_ticks(self) -> int:
        """Ticks per trial, N = round(2·cycle_s/ts_s) + 1 (pick → place → pick, the end point
        included; :func:`host.planning.journeys.trial_samples`, which also checks that the cycle
        is a whole number of periods)."""
        return 2 * max(int(round(self.cycle_s / self.ts_s)), 1) + 1

    def as_dict(self) -> dict[str, Any]:
        """The configuration as plain values (``law_options`` only when there are any, ``plant``
        only when a factor differs from 1)."""
        d = dataclasses.asdict(self)
        d["gains"] = dataclasses.asdict(self.gains)
        if not self.law_options:
            d.pop("law_options")
        else:
            d["law_options"] = dict(self.law_options)
        if self.plant.identity:
            d.pop("plant")
        else:
            d["plant"] = dataclasses.asdict(self.plant)
        return d


_TOP_KEYS = {f.name for f in dataclasses.fields(ExperimentConfig)}
_GAIN_KEYS = {f.name for f in dataclasses.fields(GainSpec)} - {"name"} | {"preset"}
#: the keys of the ``[plant]`` table
PLANT_KEYS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(PlantScales))


def _check_number(name: str, v: Any, *, integer: bool = False) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (integer and not isinstance(v, int)):
        raise ConfigError(f"{name} must be {'an integer' if integer else 'a number'}, got {v!r}")
    if not math.isfinite(float(v)):
        raise ConfigError(f"{name} must be finite, got {v!r}")


def _check_positive(name: str, v: Any, unit: str = "", *, integer: bool = False) -> None:
    """:func:`_check_number`, and > 0 (``unit``: how the message names its unit, e.g. `` bit/s``)."""
    _check_number(name, v, integer=integer)
    if v <= 0:
        raise ConfigError(f"{name} must be > 0{unit}, got {v}")


def _check_str(name: str, v: Any) -> None:
    if not isinstance(v, str):
        raise ConfigError(f"{name} must be a string, got {v!r}")


def _gain_spec(table: Mapping[str, Any], where: str = "") -> GainSpec:
    unknown = set(table) - _GAIN_KEYS
    if unknown:
        raise ConfigError(f"{where}unknown key(s) in [gains]: {', '.join(sorted(unknown))}")
    preset = table.get("preset", "normalized")
    if not isinstance(preset, str) or preset not in GAIN_PRESETS:
        raise ConfigError(f"{where}unknown gain preset {preset!r}; choose one of {', '.join(GAIN_PRESETS)}")
    base = GAIN_PRESETS[preset]
    changes: dict[str, Any] = {}
    for k, v in table.items():
        if k == "preset":
            continue
        if v is None:
            changes[k] = None
            continue
        try:
            _check_number(f"gains.{k}", v, integer=k in ("lead", "q_order"))
        except ConfigError as err:
            raise ConfigError(f"{where}{err}") from None
        changes[k] = v
    if changes:
        changes["name"] = f"{preset}+custom"
    return dataclasses.replace(base, **changes)


def _plant_scales(table: Any, where: str = "") -> PlantScales:
    """The ``[plant]`` table (or a :class:`PlantScales`) as a :class:`PlantScales`."""
    if isinstance(table, PlantScales):
        return table
    if not isinstance(table, Mapping):
        raise ConfigError(f"{where}plant must be a table ([plant] with keys such as mass_scale), got {table!r}")
    unknown = set(table) - set(PLANT_KEYS)
    if unknown:
        raise ConfigError(f"{where}unknown key(s) in [plant]: {', '.join(sorted(unknown))}; choose from {', '.join(PLANT_KEYS)}")
    for k, v in table.items():
        try:
            _check_number(f"plant.{k}", v)
        except ConfigError as err:
            raise ConfigError(f"{where}{err}") from None
    try:
        return PlantScales(**{k: float(v) for k, v in table.items()})
    except ValueError as err:
        raise ConfigError(f"{where}{err}") from None


def _read_toml(p: Path) -> dict[str, Any]:
    """The TOML file ``p`` as a dict; every problem is one line naming the file."""
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {p}") from None
    except IsADirectoryError:
        raise ConfigError(f"config file {p} is a folder, not a TOML file") from None
    except OSError as err:
        raise ConfigError(f"cannot read config file {p}: {err.strerror or err}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError(f"config file {p} is not a text (UTF-8) TOML file") from None
    if "\x00" in text:
        raise ConfigError(f"config file {p} is not a text (UTF-8) TOML file (it holds NUL bytes)")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {p} is not valid TOML: {exc}") from None


def build_config(toml_path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> ExperimentConfig:
    """Merge defaults < TOML file < ``overrides`` (CLI options that were given) and validate.

    ``overrides["gains"]`` may be a dict of ``[gains]`` keys (merged over the file's table) or a
    :class:`GainSpec` (replaces it).
    """
    data: dict[str, Any] = {}
    where = ""
    base_dir: Path | None = None
    if toml_path is not None:
        p = Path(toml_path)
        data = _read_toml(p)
        where = f"config file {p}: "
        base_dir = p.resolve().parent
        unknown = set(data) - _TOP_KEYS
        if unknown:
            raise ConfigError(f"{where}unknown key(s): {', '.join(sorted(unknown))}")
        if "gains" in data and not isinstance(data["gains"], dict):
            raise ConfigError(f"{where}gains must be a table ([gains] with keys such as alpha, lp), got {data['gains']!r}")
        if "law_options" in data and not isinstance(data["law_options"], dict):
            raise ConfigError(
                f"{where}law_options must be a table ([law_options] with the law's options), got {data['law_options']!r}"
            )
        if "plant" in data and not isinstance(data["plant"], dict):
            raise ConfigError(f"{where}plant must be a table ([plant] with keys such as mass_scale), got {data['plant']!r}")
        if "path" in data:
            path = data["path"]
            if isinstance(path, bool) or not isinstance(path, (str, int)):
                raise ConfigError(f"{where}path must be 1-4 or a path file name, got {path!r}")
            path = str(path)
            if path not in _BUILTIN_PATH_NAMES and not Path(path).is_absolute():
                path = str(base_dir / path)  # relative to the config file's folder
            data["path"] = path
        for k in ("law", "profile", "disturbance", "ff0"):
            if k in data:
                try:
                    _check_str(k, data[k])
                except ConfigError as err:
                    raise ConfigError(f"{where}{err}") from None
    file_gains = data.get("gains", {})
    from_file = {k for k in data if k != "gains"} | {f"gains.{k}" for k in (file_gains or {})}
    for k, v in (overrides or {}).items():
        if v is not None:
            from_file -= {k} if k != "gains" else {f"gains.{g}" for g in (v if isinstance(v, Mapping) else {})}
        if v is None:
            continue
        if k == "gains" and isinstance(v, Mapping) and isinstance(file_gains, dict):
            data["gains"] = {**file_gains, **v}
        elif k == "law_options" and isinstance(v, Mapping) and isinstance(data.get("law_options", {}), dict):
            data["law_options"] = {**data.get("law_options", {}), **v}
        elif k == "plant" and isinstance(v, Mapping) and isinstance(data.get("plant", {}), dict):
            data["plant"] = {**data.get("plant", {}), **v}
        else:
            data[k] = v
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise ConfigError(f"unknown key(s): {', '.join(sorted(unknown))}")
    gains_table = data.pop("gains", {})
    if isinstance(gains_table, GainSpec):
        spec = gains_table
    else:
        if not isinstance(gains_table, dict):
            raise ConfigError(f"{where}gains must be a table ([gains] with keys such as alpha, lp), got {gains_table!r}")
        spec = _gain_spec(gains_table, where if file_gains else "")
    if "path" in data:
        if isinstance(data["path"], bool) or not isinstance(data["path"], (str, int, Path)):
            raise ConfigError(f"path must be 1-4 or a path file name, got {data['path']!r}")
        data["path"] = str(data["path"])
    if "law_options" in data:
        opts = data["law_options"]
        if not isinstance(opts, Mapping):
            raise ConfigError(f"law_options must be a table of the law's options, got {opts!r}")
        data["law_options"] = dict(opts)
    if "plant" in data:
        data["plant"] = _plant_scales(data["plant"], where if "plant" in from_file else "")
    try:
        cfg = ExperimentConfig(**data, gains=spec)
        validate(cfg)
    except ConfigError as err:
        text = str(err)
        if where and not text.startswith(where) and _key_of(text) in from_file:
            text = where + text  # the value came from the file: name it
        raise ConfigError(text) from None
    return cfg


def gains_table(spec: GainSpec) -> dict[str, Any]:
    """A :class:`GainSpec` as a ``[gains]`` table: its preset and the values that differ from it
    (``build_config`` makes the same spec of it, name included)."""
    base_name = spec.name.split("+")[0]
    if base_name not in GAIN_PRESETS:
        base_name = "normalized"
    base = GAIN_PRESETS[base_name]
    table: dict[str, Any] = {"preset": base_name}
    for f in dataclasses.fields(GainSpec):
        if f.name != "name" and getattr(spec, f.name) != getattr(base, f.name):
            table[f.name] = getattr(spec, f.name)
    return table


def _key_of(message: str) -> str:
    """The configuration key a validation message is about (its first word, or the word after
    ``unknown``)."""
    words = message.split()
    if len(words) > 1 and words[0] == "unknown":
        return {"gain": "gains.preset"}.get(words[1], words[1])
    return words[0] if words else ""


def validate(cfg: ExperimentConfig) -> None:
    """Raise :class:`ConfigError` on any value that cannot run."""
    for name in ("law", "path", "profile", "disturbance", "ff0"):
        _check_str(name, getattr(cfg, name))
    try:
        check_law_name(cfg.law)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    if not isinstance(cfg.law_options, Mapping):
        raise ConfigError(f"law_options must be a table of the law's options, got {cfg.law_options!r}")
    for key, value in cfg.law_options.items():
        if not isinstance(key, str) or not key:
            raise ConfigError(f"law_options: option names must be non-empty strings, got {key!r}")
        if not isinstance(value, (str, bool)):
            _check_number(f"law_options.{key}", value)
    _check_number("iterations", cfg.iterations, integer=True)
    if not 1 <= cfg.iterations <= MAX_ITERATIONS:
        raise ConfigError(f"iterations must be between 1 and {MAX_ITERATIONS}, got {cfg.iterations}")
    _check_positive("cycle_s", cfg.cycle_s)
    if cfg.profile not in PROFILES:
        raise ConfigError(f"unknown profile {cfg.profile!r}; choose one of {', '.join(PROFILES)}")
    if cfg.disturbance not in DISTURBANCES:
        raise ConfigError(f"unknown disturbance {cfg.disturbance!r}; choose one of {', '.join(DISTURBANCES)}")
    _check_number("seed", cfg.seed, integer=True)
    if not 0 <= cfg.seed <= MAX_SEED:
        raise ConfigError(f"seed must be 0..{MAX_SEED}, got {cfg.seed}")
    _check_number("ts_s", cfg.ts_s)
    if not 1e-4 <= cfg.ts_s <= 1e-2:
        raise ConfigError(f"ts_s must be between 0.0001 and 0.01 s, got {cfg.ts_s}")
    _check_number("substeps", cfg.substeps, integer=True)
    if not 1 <= cfg.substeps <= 100:
        raise ConfigError(f"substeps must be between 1 and 100, got {cfg.substeps}")
    if cfg.ff0 not in ("model", "zero"):
        raise ConfigError(f"ff0 must be 'model' or 'zero', got {cfg.ff0!r}")
    _check_positive("following_error_deg", cfg.following_error_deg)
    if cfg.ff_transport not in FF_TRANSPORTS:
        raise ConfigError(f"ff_transport must be one of {', '.join(FF_TRANSPORTS)}, got {cfg.ff_transport!r}")
    _check_positive("fieldbus_bitrate", cfg.fieldbus_bitrate, " bit/s", integer=True)
    if not isinstance(cfg.force_bus_fit, bool):
        raise ConfigError(f"force_bus_fit must be true or false, got {cfg.force_bus_fit!r}")
    if cfg.ff_transport == "pdo":
        fit = cyclic_bus_fit(cfg.ts_s, cfg.fieldbus_bitrate)
        if not fit.fits and not cfg.force_bus_fit:
            raise ConfigError(
                f"the cyclic PDO exchange does not fit the fieldbus: {fit.message()}; a real master would "
                "lower the control rate, map fewer objects or use several PDOs per drive at a lower rate "
                "(docs/timing.md §7); --force-bus-fit runs it anyway"
            )
    g = cfg.gains
    for f in dataclasses.fields(GainSpec):
        v = getattr(g, f.name)
        if f.name == "name" or v is None:
            continue
        _check_number(f"gains.{f.name}", v, integer=f.name in ("lead", "q_order"))
        if v < 0:
            raise ConfigError(f"gains.{f.name} must be >= 0, got {v}")
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


# -- writing an experiment file ------------------------------------------------------------------

#: the tables of an experiment file, in the order they are written
_TOML_TABLES = ("gains", "law_options", "plant")


def toml_value(v: Any) -> str:
    """One value as TOML: booleans, integers, floats (``repr``: exact; ``inf``/``nan`` as TOML
    writes them) and strings (a TOML basic string).

    :raises ValueError: a value TOML has no literal for (None, a list, …)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(v, str):
        import json

        return json.dumps(v, ensure_ascii=False)  # a JSON string is a TOML basic string
    raise ValueError(f"no TOML value for {v!r}")


def options_toml(options: Mapping[str, Any]) -> str:
    """Experiment options (the keys of this file's TOML layout) as an experiment file: the top-level
    keys, then ``[gains]``, ``[law_options]``, ``[plant]`` (left out when empty); ``None`` values
    are left out (the default holds)."""
    lines = [f"{k} = {toml_value(v)}" for k, v in options.items() if k not in _TOML_TABLES and v is not None]
    for table in _TOML_TABLES:
        values = {k: v for k, v in (options.get(table) or {}).items() if v is not None}
        if values:
            lines += ["", f"[{table}]"] + [f"{k} = {toml_value(v)}" for k, v in values.items()]
    return "\n".join(lines) + "\n"


def config_toml(config: ExperimentConfig) -> str:
    """The configuration as the TOML file of the command line (:func:`build_config` of it gives the
    same configuration: exact floats, the gains as their ``[gains]`` table, a path file as an
    absolute path)."""
    options = config.as_dict() | {"gains": gains_table(config.gains)}
    if str(options["path"]) not in _BUILTIN_PATH_NAMES:
        options["path"] = str(Path(str(options["path"])).resolve())
    return options_toml(options)

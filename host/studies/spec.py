"""What a sweep runs: its points, from a TOML spec and/or the command line.

This module owns :class:`SweepSpec` (the base options, the grid, the Monte Carlo draws),
:class:`Point` (one experiment of a sweep: its options and the values that set it apart),
:func:`parse_assignment` (``KEY=V1,V2,…``) and the spec file format:

.. code-block:: toml

    [base]                  # the options every point shares: the keys of an experiment file
    law = "pd-ilc-q"        # (`ilcrig sim --config`); a table such as [base.gains] works too
    iterations = 10
    "gains.alpha" = 3.0     # or a dotted key

    [vary]                  # the grid: the product of every key's values
    "gains.alpha" = [2.0, 3.0, 4.0]                              # a list
    cycle_s = { start = 0.15, stop = 0.35, step = 0.05 }         # a range, both ends included
    "gains.lp_norm" = { start = 2e-4, stop = 5e-3, num = 5, log = true }  # num values, log-spaced

    [monte_carlo]           # seeded random draws: `samples` of them per grid point
    samples = 100
    seed = 1                # the draws of sample s: numpy.random.default_rng([seed, 0x4D43, s])
    [monte_carlo.draw]
    "plant.inertia_scale" = { uniform = [0.8, 1.2] }     # low, high
    "plant.mass_scale" = { normal = [1.0, 0.05] }        # mean, standard deviation
    "plant.friction_scale" = { lognormal = [0.0, 0.3] }  # mean and sd of the logarithm
    "seed" = { integers = [0, 100000] }                  # low, high (exclusive)
    "law" = { choice = ["pd-ilc", "pd-ilc-q"] }

A key is an experiment key (``law``, ``cycle_s``, …: ``ilcrig.Experiment``'s), or a dotted key into
one of its tables: ``gains.KEY``, ``law_options.KEY``, ``plant.KEY`` (the plant-uncertainty factors
``inertia_scale``, ``mass_scale``, ``friction_scale``, ``payload_scale``).  Precedence: the command
line's ``--set`` over ``[base]`` over ``--config`` (an experiment file); a key may be varied or
drawn, not both, and not also set.

A point's draws depend only on the seed and its sample index (adding samples keeps the earlier
ones).  Its id is a digest of its complete, validated configuration: a point is the same point in
any sweep that runs the same experiment, which is what makes a sweep folder resumable.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import math
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bus.errors import InputError
from host.experiment.config import PLANT_KEYS, ExperimentConfig, build_config

logger = logging.getLogger(__name__)

__all__ = [
    "SweepSpec",
    "Point",
    "parse_assignment",
    "parse_value",
    "set_key",
    "DRAW_PURPOSE",
    "DISTRIBUTIONS",
]

#: the purpose word of the Monte Carlo generator (docs/architecture.md §4.5: one generator per
#: seed, purpose and index)
DRAW_PURPOSE = 0x4D43  # "MC"
#: the distributions of ``[monte_carlo.draw]`` and the number of parameters each takes
DISTRIBUTIONS: dict[str, int] = {"uniform": 2, "loguniform": 2, "normal": 2, "lognormal": 2, "integers": 2, "choice": -1}
_TABLES = ("gains", "law_options", "plant")
_TOP_KEYS = frozenset(f for f in ExperimentConfig.__dataclass_fields__ if f not in _TABLES)
#: spec-file sections
_SECTIONS = frozenset({"base", "vary", "monte_carlo", "tune", "objective"})
#: the most points one sweep may have
MAX_POINTS = 1_000_000


def parse_value(raw: str) -> Any:
    """A command-line value as TOML reads it (numbers, booleans, quoted strings), else the text."""
    raw = raw.strip()
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        return raw


def parse_assignment(text: str, option: str = "--vary") -> tuple[str, list[Any]]:
    """``KEY=V1,V2,…`` → (key, values).

    :raises InputError: no ``=``, no key, or no value (one line naming the option).
    """
    key, eq, raw = text.partition("=")
    key = key.strip()
    values = [parse_value(v) for v in raw.split(",") if v.strip()] if eq else []
    if not key or not values:
        raise InputError(f"{option} {text!r}: expected KEY=VALUE[,VALUE…]")
    check_key(key, option)
    return key, values


def check_key(key: str, where: str) -> None:
    """:raises InputError: ``key`` is not an experiment key or a dotted key into one of its tables."""
    head, dot, tail = key.partition(".")
    if dot:
        if head not in _TABLES or not tail or "." in tail:
            raise InputError(f"{where}: {key!r} is not an option; a dotted key is gains.KEY, law_options.KEY or plant.KEY")
        if head == "plant" and tail not in PLANT_KEYS:
            raise InputError(f"{where}: unknown plant factor {tail!r}; choose from {', '.join(PLANT_KEYS)}")
    elif key not in _TOP_KEYS:
        if key in _TABLES:
            raise InputError(f"{where}: {key!r} is a table; vary its keys ({key}.KEY)")
        raise InputError(f"{where}: unknown option {key!r}; choose from {', '.join(sorted(_TOP_KEYS))} or a dotted key")


def set_key(options: dict[str, Any], key: str, value: Any) -> None:
    """``options[key] = value`` for a plain or dotted key (into ``gains``, ``law_options``, ``plant``)."""
    head, dot, tail = key.partition(".")
    if dot:
        table = dict(options.get(head) or {})
        table[tail] = value
        options[head] = table
    else:
        options[key] = value


def _flatten(table: Mapping[str, Any], where: str) -> dict[str, Any]:
    """``[base]``: nested tables and dotted keys alike → {dotted key: value}."""
    flat: dict[str, Any] = {}
    for k, v in table.items():
        if k in _TABLES and isinstance(v, Mapping):
            for sub, sv in v.items():
                flat[f"{k}.{sub}"] = sv
        else:
            flat[k] = v
    for k in flat:
        check_key(k, where)
    return flat


def _range_values(key: str, spec: Mapping[str, Any], where: str) -> list[Any]:
    """The values of a range table ``{start, stop, step}`` or ``{start, stop, num[, log]}``."""
    allowed = {"start", "stop", "step", "num", "log"}
    unknown = set(spec) - allowed
    if unknown or "start" not in spec or "stop" not in spec or ("step" in spec) == ("num" in spec):
        raise InputError(f"{where} {key}: a range is {{start, stop, step}} or {{start, stop, num[, log = true]}}")
    start, stop = spec["start"], spec["stop"]
    for name, v in (("start", start), ("stop", stop)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise InputError(f"{where} {key}: {name} must be a number, got {v!r}")
    integer = isinstance(start, int) and isinstance(stop, int)
    if "num" in spec:
        num = spec["num"]
        if isinstance(num, bool) or not isinstance(num, int) or num < 1:
            raise InputError(f"{where} {key}: num must be an integer >= 1, got {num!r}")
        if spec.get("log", False):
            if start <= 0 or stop <= 0:
                raise InputError(f"{where} {key}: a log range needs start and stop > 0")
            vals = np.geomspace(float(start), float(stop), num)
        else:
            vals = np.linspace(float(start), float(stop), num)
        out = [float(v) for v in vals]
        return sorted({int(round(v)) for v in out}) if integer else out
    step = spec["step"]
    if isinstance(step, bool) or not isinstance(step, (int, float)) or not step > 0:
        raise InputError(f"{where} {key}: step must be a number > 0, got {step!r}")
    if spec.get("log", False):
        raise InputError(f"{where} {key}: log takes num, not step")
    count = int(math.floor((stop - start) / step + 1e-9)) + 1
    if count < 1:
        raise InputError(f"{where} {key}: stop must be >= start, got {start} .. {stop}")
    if integer and isinstance(step, int):
        return [start + i * step for i in range(count)]
    return [round(float(start) + i * float(step), 12) for i in range(count)]


def _vary_values(key: str, value: Any, where: str) -> list[Any]:
    if isinstance(value, list):
        if not value:
            raise InputError(f"{where} {key}: no values")
        return list(value)
    if isinstance(value, Mapping):
        return _range_values(key, value, where)
    return [value]


@dataclass(frozen=True)
class Draw:
    """One ``[monte_carlo.draw]`` entry: a distribution and its parameters."""

    key: str
    dist: str
    params: tuple[Any, ...]

    def sample(self, rng: np.random.Generator) -> Any:
        p = self.params
        if self.dist == "uniform":
            return float(rng.uniform(p[0], p[1]))
        if self.dist == "loguniform":
            return float(math.exp(rng.uniform(math.log(p[0]), math.log(p[1]))))
        if self.dist == "normal":
            return float(rng.normal(p[0], p[1]))
        if self.dist == "lognormal":
            return float(rng.lognormal(p[0], p[1]))
        if self.dist == "integers":
            return int(rng.integers(p[0], p[1]))
        return p[int(rng.integers(0, len(p)))]  # choice

    @classmethod
    def parse(cls, key: str, value: Any, where: str) -> Draw:
        if not isinstance(value, Mapping) or len(value) != 1:
            raise InputError(f"{where} {key}: a draw is one {{DISTRIBUTION = [parameters]}}: {', '.join(DISTRIBUTIONS)}")
        ((dist, params),) = value.items()
        if dist not in DISTRIBUTIONS:
            raise InputError(f"{where} {key}: unknown distribution {dist!r}; choose from {', '.join(DISTRIBUTIONS)}")
        if not isinstance(params, list) or not params:
            raise InputError(f"{where} {key}: {dist} takes a list of parameters")
        n = DISTRIBUTIONS[dist]
        if n >= 0:
            if len(params) != n or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in params):
                raise InputError(f"{where} {key}: {dist} takes {n} numbers, got {params!r}")
            a, b = params
            if dist in ("uniform", "loguniform", "integers") and not a < b:
                raise InputError(f"{where} {key}: {dist} needs low < high, got {params!r}")
            if dist == "loguniform" and a <= 0:
                raise InputError(f"{where} {key}: loguniform needs low > 0, got {params!r}")
            if dist in ("normal", "lognormal") and b < 0:
                raise InputError(f"{where} {key}: {dist} needs a standard deviation >= 0, got {params!r}")
            if dist == "integers" and not (isinstance(a, int) and isinstance(b, int)):
                raise InputError(f"{where} {key}: integers takes two integers, got {params!r}")
        return cls(key, dist, tuple(params))


@dataclass(frozen=True)
class Point:
    """One experiment of a sweep.

    :ivar id: its folder name in the sweep (``pt-`` + a digest of the configuration, or a name the
        sweep gives it, as ``ilcrig reproduce`` does)
    :ivar index: its place in the sweep's order
    :ivar options: the experiment's keys (``ilcrig.Experiment(**options)``)
    :ivar labels: what sets it apart: {varied or drawn key: value}, and ``sample`` (the Monte Carlo
        sample index) when the sweep draws
    :ivar config: the validated configuration
    """

    id: str
    index: int
    options: dict[str, Any]
    labels: dict[str, Any]
    config: ExperimentConfig = field(compare=False, repr=False)

    @staticmethod
    def config_id(cfg: ExperimentConfig) -> str:
        """``pt-`` + 12 hex digits of the SHA-256 of the configuration (canonical JSON)."""
        text = json.dumps(cfg.as_dict(), sort_keys=True, separators=(",", ":"))
        return "pt-" + hashlib.sha256(text.encode()).hexdigest()[:12]

    @classmethod
    def of(
        cls, options: Mapping[str, Any], *, index: int = 0, labels: Mapping[str, Any] | None = None, name: str | None = None
    ) -> Point:
        """The point of ``options`` (validated: :class:`InputError` with the configuration's message)."""
        opts = dict(options)
        try:
            cfg = build_config(None, opts)
        except (ValueError, FileNotFoundError) as exc:
            where = ", ".join(f"{k} = {v!r}" for k, v in (labels or {}).items())
            raise InputError(f"{exc}" + (f" (point {where})" if where else "")) from None
        return cls(name or cls.config_id(cfg), index, opts, dict(labels or {}), cfg)


@dataclass
class SweepSpec:
    """A sweep: base options, a grid (:attr:`vary`: key → values, the product) and Monte Carlo draws
    (:attr:`draws`, :attr:`samples` per grid point, :attr:`seed`).  :meth:`points` expands it."""

    base: dict[str, Any] = field(default_factory=dict)
    vary: dict[str, list[Any]] = field(default_factory=dict)
    draws: list[Draw] = field(default_factory=list)
    samples: int = 0
    seed: int = 0
    config_file: Path | None = None
    #: the other sections of the file (``[tune]``, ``[objective]``), for ``ilcrig tune``
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_toml(cls, path: str | Path) -> SweepSpec:
        """Read a spec file (module docstring).

        :raises InputError: unreadable file, unknown section or key, bad range or draw.
        """
        p = Path(path)
        try:
            data = tomllib.loads(p.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(f"sweep spec not found: {p}") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"cannot read sweep spec {p}: {exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"sweep spec {p} is not valid TOML: {exc}") from None
        unknown = set(data) - _SECTIONS
        if unknown:
            raise InputError(
                f"sweep spec {p}: unknown section(s) {', '.join(sorted(unknown))}; choose from {', '.join(sorted(_SECTIONS))}"
            )
        where = f"sweep spec {p}:"
        spec = cls()
        base = data.get("base", {})
        if not isinstance(base, Mapping):
            raise InputError(f"{where} [base] must be a table")
        spec.base = _flatten(base, f"{where} [base]")
        if "path" in spec.base and isinstance(spec.base["path"], str) and spec.base["path"] not in ("1", "2", "3", "4"):
            if not Path(spec.base["path"]).is_absolute():  # a path file: relative to the spec's folder
                spec.base["path"] = str(p.resolve().parent / spec.base["path"])
        vary = data.get("vary", {})
        if not isinstance(vary, Mapping):
            raise InputError(f"{where} [vary] must be a table")
        for k, v in vary.items():
            check_key(k, f"{where} [vary]")
            spec.vary[k] = _vary_values(k, v, f"{where} [vary]")
        mc = data.get("monte_carlo", {})
        if not isinstance(mc, Mapping):
            raise InputError(f"{where} [monte_carlo] must be a table")
        bad = set(mc) - {"samples", "seed", "draw"}
        if bad:
            raise InputError(f"{where} [monte_carlo]: unknown key(s) {', '.join(sorted(bad))}; choose from samples, seed, draw")
        spec.samples = _int(mc.get("samples", 0), f"{where} [monte_carlo] samples", 0)
        spec.seed = _int(mc.get("seed", 0), f"{where} [monte_carlo] seed", 0)
        draw = mc.get("draw", {})
        if not isinstance(draw, Mapping):
            raise InputError(f"{where} [monte_carlo.draw] must be a table")
        for k, v in draw.items():
            check_key(k, f"{where} [monte_carlo.draw]")
            spec.draws.append(Draw.parse(k, v, f"{where} [monte_carlo.draw]"))
        spec.extra = {k: v for k, v in data.items() if k in ("tune", "objective")}
        spec._check_overlap(where)
        return spec

    def add_cli(self, sets: Iterable[str] = (), varies: Iterable[str] = (), config: str | Path | None = None) -> None:
        """Merge the command line: ``--set KEY=VALUE`` (repeatable), ``--vary KEY=V1,V2,…``
        (repeatable) and ``--config`` (an experiment file under everything)."""
        for text in sets:
            key, values = parse_assignment(text, "--set")
            if len(values) != 1:
                raise InputError(f"--set {text!r}: one value (use --vary for several)")
            self.base[key] = values[0]
        for text in varies:
            key, values = parse_assignment(text, "--vary")
            self.vary[key] = values
        if config is not None:
            self.config_file = Path(config)
        self._check_overlap("")

    def _check_overlap(self, where: str) -> None:
        drawn = {d.key for d in self.draws}
        both = (set(self.vary) & drawn) | (set(self.base) & (set(self.vary) | drawn))
        if both:
            raise InputError(f"{where + ' ' if where else ''}{', '.join(sorted(both))}: set, varied or drawn more than once")
        if self.config_file is not None and not self.config_file.is_file():
            raise InputError(f"config file not found: {self.config_file}")

    @property
    def varied_keys(self) -> list[str]:
        """The keys that set points apart: the grid's, then the draws'."""
        return list(self.vary) + [d.key for d in self.draws]

    @property
    def n_points(self) -> int:
        n = math.prod(len(v) for v in self.vary.values())
        return n * max(self.samples, 1)

    def base_options(self) -> dict[str, Any]:
        """The options every point shares: ``--config``'s, under ``[base]`` and ``--set``."""
        opts: dict[str, Any] = {}
        if self.config_file is not None:
            try:
                cfg = build_config(self.config_file)
            except (ValueError, FileNotFoundError) as exc:
                raise InputError(str(exc)) from None
            opts = cfg.as_dict()
            opts["gains"] = _gains_keys(cfg)
        for k, v in self.base.items():
            set_key(opts, k, v)
        return opts

    def draw(self, sample: int) -> dict[str, Any]:
        """The values of Monte Carlo sample ``sample`` (key order as in the spec)."""
        rng = np.random.default_rng([self.seed, DRAW_PURPOSE, sample])
        return {d.key: d.sample(rng) for d in self.draws}

    def points(self) -> list[Point]:
        """Every point: the grid (in the order of its keys, the last one fastest) times the samples,
        each validated, without duplicates (two equal configurations are one point).

        :raises InputError: a point that is not a valid experiment, or too many points.
        """
        if self.draws and self.samples < 1:
            raise InputError("[monte_carlo] draws need samples >= 1 (or --samples N)")
        if self.n_points > MAX_POINTS:
            raise InputError(f"the sweep has {self.n_points} points; at most {MAX_POINTS}")
        base = self.base_options()
        keys = list(self.vary)
        samples: Sequence[int | None] = range(self.samples) if self.samples > 0 else [None]
        draws = {s: self.draw(s) for s in samples if s is not None}
        out: list[Point] = []
        seen: set[str] = set()
        for combo in itertools.product(*(self.vary[k] for k in keys)):
            for s in samples:
                opts = json.loads(json.dumps(base))
                labels: dict[str, Any] = {}
                for k, v in zip(keys, combo):
                    set_key(opts, k, v)
                    labels[k] = v
                if s is not None:
                    for k, v in draws[s].items():
                        set_key(opts, k, v)
                        labels[k] = v
                    labels["sample"] = s
                point = Point.of(opts, index=len(out), labels=labels)
                if point.id in seen:
                    continue
                seen.add(point.id)
                out.append(point)
        return out


def _gains_keys(cfg: ExperimentConfig) -> dict[str, Any]:
    from host.experiment.config import gains_table

    return gains_table(cfg.gains)


def _int(v: Any, where: str, low: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < low:
        raise InputError(f"{where} must be an integer >= {low}, got {v!r}")
    return v

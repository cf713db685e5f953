"""What an experiment says on the terminal, and the options that define it.

This module owns the experiment options of the command line (:data:`EXPERIMENT_OPTIONS`, one
definition: :mod:`host.cli.options` builds ``sim``'s, ``run``'s and ``host``'s parsers from it, the
launcher passes them on to the host role with it), their typed values (:class:`ExperimentOptions`:
what the command line hands down, never its parsed namespace), the translation of those into
an :class:`~host.experiment.config.ExperimentConfig` (:func:`experiment_config`) and of that into
the plan (:func:`prepared`: what the plan refuses is :class:`bus.errors.InputError`), and the
console lines of a run: the plan with its convergence check, one row of RMSE/MaxE per trial, and
the closing line.  It is kept
import-light: every role parses the command line.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any, TextIO

from bus.errors import InputError
from host.learning.names import DEFAULT_LAW, GAIN_PRESET_NAMES, LAWS, MAX_ITERATIONS
from host.planning.task_plan import PROFILES

if TYPE_CHECKING:
    from host.experiment.config import ExperimentConfig
    from host.experiment.plan import Plan
    from host.learning.metrics import TrialMetrics

__all__ = [
    "EXPERIMENT_OPTIONS",
    "ExperimentOption",
    "ExperimentOptions",
    "experiment_config",
    "parse_law_options",
    "prepared",
    "check_line",
    "print_plan",
    "print_header",
    "print_row",
]


#: the disturbance kinds (one definition: ``plant.disturbance.KINDS``, whose import is heavy
#: enough that the help text lists them here; a test checks that both agree)
_DISTURBANCE_HELP = "none, repetitive, nonrepetitive, both"


@dataclass(frozen=True)
class ExperimentOption:
    """One experiment option of the command line (``ilcrig sim``, ``run``, ``host``): its flag, the
    attribute it is parsed into, its help, the type of its value (None: the text) and whether it is
    a switch without a value.  :mod:`host.cli.options` builds the parser from these;
    :mod:`host.rig.role_commands` passes the given ones on to the host role."""

    flag: str
    dest: str
    help: str
    type: Callable[[str], Any] | None = None
    metavar: str | None = None
    switch: bool = False


def _gain_options() -> tuple[ExperimentOption, ...]:
    out = [
        ExperimentOption(f"--{name}", f"g_{name.replace('-', '_')}", hlp, float)
        for name, hlp in (
            ("alpha", "α of the paper's law (feedback Kp = (α−1)Lp)"),
            ("beta", "β of the paper's law (feedback Kd = (β−1)Ld)"),
            ("lp", "learning P gain, N·m/rad (overrides lp_norm)"),
            ("ld", "learning D gain, N·m·s/rad (overrides ld_norm)"),
            ("lp-norm", "Lp·Ts²/I_joint"),
            ("ld-norm", "Ld·Ts/I_joint"),
            ("q-cutoff-hz", "Q-filter cut-off of q-ilc, Hz"),
            ("pdq-cutoff-hz", "Q-filter cut-off of pd-ilc-q, Hz"),
        )
    ]
    out.append(ExperimentOption("--lead", "g_lead", "learning lead in samples (default 1)", int))
    return tuple(out)


def _plant_options() -> tuple[ExperimentOption, ...]:
    return tuple(
        ExperimentOption(
            f"--{name}-scale",
            f"p_{name}_scale",
            f"plant uncertainty: the emulated robot's {what} times FACTOR ([plant] {name}_scale, default 1)",
            float,
            "FACTOR",
        )
        for name, what in (
            ("inertia", "rotational inertias"),
            ("mass", "link and platform masses"),
            ("friction", "Coulomb and viscous friction"),
            ("payload", "payload"),
        )
    )


#: the experiment options, in the order of ``--help`` (the run folder ``--out`` is not one of them)
EXPERIMENT_OPTIONS: tuple[ExperimentOption, ...] = (
    ExperimentOption("--config", "config", "experiment file (keys as the options; unknown keys are errors)", metavar="TOML"),
    ExperimentOption(
        "--law",
        "law",
        f"learning law: {', '.join(LAWS)} (default {DEFAULT_LAW}), an installed plug-in's name "
        "(`ilcrig laws` lists them) or module:Class",
    ),
    ExperimentOption(
        "--law-options",
        "law_options",
        "the law's own options ([law_options] of the TOML file), e.g. torque_limit_nm=200",
        metavar="KEY=VALUE[,KEY=VALUE…]",
    ),
    ExperimentOption("--iterations", "iterations", f"number of trials, 1..{MAX_ITERATIONS} (default 10)", int),
    ExperimentOption("--path", "path", "1-4 or a path TOML file (default 1)"),
    ExperimentOption("--cycle", "cycle_s", "single-journey time in s (default 0.25)", float),
    ExperimentOption("--profile", "profile", f"motion law: {', '.join(PROFILES)} (default ruckig)"),
    ExperimentOption("--disturbance", "disturbance", f"{_DISTURBANCE_HELP} (default none)"),
    ExperimentOption("--seed", "seed", "seed of every random generator (default 0)", int),
    ExperimentOption("--ff0", "ff0", "initial feed-forward: model | zero (default model)"),
    ExperimentOption("--gains", "preset", f"gain preset: {', '.join(GAIN_PRESET_NAMES)} (default normalized)"),
    *_gain_options(),
    ExperimentOption(
        "--ff-transport",
        "ff_transport",
        "feed-forward transport: table (SDO tables before each trial) | pdo (CiA 402 CSP, "
        "SYNC + RPDO/TPDO every tick) (default table)",
    ),
    ExperimentOption(
        "--fieldbus-bitrate", "fieldbus_bitrate", "fieldbus bit rate in bit/s for the bus-fit check (default 1000000)", int
    ),
    ExperimentOption(
        "--force-bus-fit",
        "force_bus_fit",
        "run a pdo configuration even if its cyclic frames do not fit the fieldbus",
        switch=True,
    ),
    *_plant_options(),
)


#: the keys of :class:`ExperimentOptions` that go to the configuration as they are
_PLAIN_KEYS = (
    "law",
    "iterations",
    "path",
    "cycle_s",
    "profile",
    "disturbance",
    "seed",
    "ff0",
    "ff_transport",
    "fieldbus_bitrate",
    "force_bus_fit",
)
#: the prefixes of the :attr:`ExperimentOption.dest` of the gain and plant-uncertainty options
_GAIN_PREFIX, _PLANT_PREFIX = "g_", "p_"


@dataclass(frozen=True)
class ExperimentOptions:
    """The experiment options as given on a command line (None: not given, the file's or the
    default value applies): what :func:`experiment_config` builds the configuration from and what
    ``ilcrig run`` passes on to its host role (:meth:`given`).

    :ivar config: ``--config``, the experiment TOML file
    :ivar law_options: ``--law-options`` as given (``KEY=VALUE[,KEY=VALUE…]``)
    :ivar cycle_s: ``--cycle``, s
    :ivar fieldbus_bitrate: ``--fieldbus-bitrate``, bit/s
    :ivar preset: ``--gains``, the gain preset
    :ivar gains: the gain options given (``alpha``, ``lp``, ``lead``, …: the ``[gains]`` keys)
    :ivar plant: the plant-uncertainty options given (``inertia_scale``, …: the ``[plant]`` keys)
    """

    config: str | None = None
    law: str | None = None
    law_options: str | None = None
    iterations: int | None = None
    path: str | None = None
    cycle_s: float | None = None
    profile: str | None = None
    disturbance: str | None = None
    seed: int | None = None
    ff0: str | None = None
    preset: str | None = None
    ff_transport: str | None = None
    fieldbus_bitrate: int | None = None
    force_bus_fit: bool | None = None
    gains: Mapping[str, float] = field(default_factory=dict)
    plant: Mapping[str, float] = field(default_factory=dict)

    @classmethod
    def from_values(cls, values: Mapping[str, Any]) -> ExperimentOptions:
        """The options of parsed values keyed by :attr:`ExperimentOption.dest` (others are ignored)."""
        plain: dict[str, Any] = {}
        gains: dict[str, Any] = {}
        plant: dict[str, Any] = {}
        for o in EXPERIMENT_OPTIONS:
            value = values.get(o.dest)
            if value is None:
                continue
            if o.dest.startswith(_GAIN_PREFIX):
                gains[o.dest.removeprefix(_GAIN_PREFIX)] = value
            elif o.dest.startswith(_PLANT_PREFIX):
                plant[o.dest.removeprefix(_PLANT_PREFIX)] = value
            else:
                plain[o.dest] = value
        return cls(**plain, gains=gains, plant=plant)

    def given(self) -> dict[str, Any]:
        """The options given, keyed by :attr:`ExperimentOption.dest`, in the order of
        :data:`EXPERIMENT_OPTIONS`."""
        values = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("gains", "plant")}
        values |= {_GAIN_PREFIX + k: v for k, v in self.gains.items()}
        values |= {_PLANT_PREFIX + k: v for k, v in self.plant.items()}
        return {o.dest: values[o.dest] for o in EXPERIMENT_OPTIONS if values.get(o.dest) is not None}


def experiment_config(options: ExperimentOptions) -> ExperimentConfig:
    """The validated configuration of the experiment options given (a ``--config`` file below them).

    :raises InputError: one-line message naming the option or file.
    """
    from host.experiment.config import build_config  # heavy (plant, learning): only when needed

    overrides: dict[str, Any] = {k: getattr(options, k) for k in _PLAIN_KEYS}
    if options.law_options is not None:
        overrides["law_options"] = parse_law_options(options.law_options)
    gains: dict[str, Any] = {}  # merged over the file's [gains] table by build_config
    if options.preset is not None:
        gains["preset"] = options.preset
    gains |= options.gains
    if gains:
        overrides["gains"] = gains
    if options.plant:
        overrides["plant"] = dict(options.plant)  # merged over the file's [plant] table
    return build_config(options.config, overrides)


def prepared(cfg: ExperimentConfig) -> Plan:
    """The plan of ``cfg`` (:func:`host.experiment.plan.prepare`) for a command: what the plan
    refuses before anything moves — an infeasible task, a point out of reach, a trial too long for
    the drives' tables or the memory — is bad input, :class:`InputError` with its first line.

    :raises InputError: the experiment cannot be run as given
    """
    from host.experiment.plan import prepare

    try:
        return prepare(cfg)
    except (ValueError, FileNotFoundError) as exc:  # the planning's refusals (plant, trajectory, plan)
        if isinstance(exc, InputError):
            raise
        raise InputError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from exc


def parse_law_options(text: str) -> dict[str, Any]:
    """``--law-options KEY=VALUE,KEY=VALUE``: values as in TOML (numbers, true/false, strings with or
    without quotes).

    :raises InputError: one line naming the option.
    """
    import tomllib

    out: dict[str, Any] = {}
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        key, eq, raw = item.partition("=")
        key, raw = key.strip(), raw.strip()
        if not eq or not key or not raw:
            raise InputError(f"--law-options {text!r}: expected KEY=VALUE[,KEY=VALUE…], got {item!r}")
        try:
            out[key] = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            out[key] = raw
    return out


def check_line(plan: Plan) -> str:
    """The plan's convergence-check line (without the newline)."""
    c = plan.check
    if not c.checked:
        return f"convergence check: not checked (law {plan.cfg.law} gives no linear iteration map)"
    return (
        f"convergence check: spectral radius {c.rho_max:.4f} ({'ok' if c.ok else 'VIOLATED: expect divergence'}), "
        f"2-norm {c.norm2:.3f} ({'monotonic' if c.norm2 < 1 else 'not monotonic'}), paper eq.(18) rho "
        f"{c.paper_rho18:.3f}; predicted error ratio after {c.iterations} trials {c.predicted_ratio:.3g}, after "
        f"{c.long_horizon} {c.predicted_ratio_long:.3g}; over {c.long_horizon} trials "
        f"{'bounded' if c.long_bounded else f'NOT bounded (grows {c.predicted_long_growth:.3g}x from its best)'}"
    )


def print_plan(stream: TextIO, role: str, plan: Plan, extra: str = "") -> None:
    """The run's first lines: the experiment and the convergence check."""
    cfg = plan.cfg
    aux = plan.law.auxiliary_trials
    aux_txt = f" ({aux} auxiliary rollouts per learning step, counted as trials)" if aux else ""
    stream.write(
        f"ilcrig {role}: law {cfg.law}, path {cfg.path}, cycle {cfg.cycle_s} s, profile {cfg.profile}, "
        f"disturbance {cfg.disturbance}, {cfg.iterations} iterations{aux_txt}, N = {plan.n_ticks} ticks/trial{extra}\n"
        f"{check_line(plan)}\n"
    )
    if plan.bus_fit is not None:
        stream.write(f"feed-forward by SYNC + PDOs (CiA 402 cyclic synchronous position); fieldbus: {plan.bus_fit['message']}\n")
    stream.flush()


def print_header(stream: TextIO) -> None:
    """The column header of the per-trial rows."""
    cols = "  ".join(f"RMSE j{j}" for j in range(1, 5)) + "  " + "  ".join(f"MaxE j{j}" for j in range(1, 5))
    stream.write(f"{'iter':>4}  {cols}   [deg]\n")


def print_row(stream: TextIO, m: TrialMetrics, role: str = "learning") -> None:
    """One trial's RMSE and MaxE per joint, degrees (an auxiliary rollout marked ``aux``)."""
    vals = "  ".join(f"{v:7.5f}" for v in m.rmse_deg) + "  " + "  ".join(f"{v:7.5f}" for v in m.max_abs_deg)
    stream.write(f"{m.k:>4}  {vals}{'   aux' if role == 'auxiliary' else ''}\n")
    stream.flush()

"""What an experiment says on the terminal, and the options that define it.

This module owns the process exit codes of every ``ilcrig`` command, the experiment options of
the command line (one definition, used by ``sim``, ``run`` and ``host`` and by the launcher that
passes them on to the host role), the translation of parsed options into an
:class:`~host.experiment.config.ExperimentConfig`, and the console lines of a run: the plan with
its convergence check, one row of RMSE/MaxE per trial, and the closing line.  It is kept
import-light: every role parses the command line.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any, TextIO

from host.learning.names import DEFAULT_LAW, GAIN_PRESET_NAMES, LAWS, MAX_ITERATIONS
from host.planning.task_plan import PROFILES

if TYPE_CHECKING:
    from host.experiment.config import ExperimentConfig
    from host.experiment.plan import Plan
    from host.learning.metrics import TrialMetrics

__all__ = [
    "add_experiment_args",
    "experiment_config",
    "parse_law_options",
    "check_line",
    "print_plan",
    "print_header",
    "print_row",
]


#: the disturbance kinds (one definition: ``plant.disturbance.KINDS``, whose import is heavy
#: enough that the help text lists them here; a test checks that both agree)
_DISTURBANCE_HELP = "none, repetitive, nonrepetitive, both"

#: the parsed options that are not part of the experiment (the launcher does not pass them on)
NOT_EXPERIMENT: frozenset[str] = frozenset({"help", "out", "bus", "hub"})


def add_experiment_args(p: argparse.ArgumentParser) -> None:
    """The experiment options (``--law``, ``--iterations``, …, ``--out``) on ``p``."""
    p.add_argument("--config", metavar="TOML", help="experiment file (keys as the options; unknown keys are errors)")
    p.add_argument(
        "--law",
        help=f"learning law: {', '.join(LAWS)} (default {DEFAULT_LAW}), an installed plug-in's name "
        "(`ilcrig laws` lists them) or module:Class",
    )
    p.add_argument(
        "--law-options",
        dest="law_options",
        metavar="KEY=VALUE[,KEY=VALUE…]",
        help="the law's own options ([law_options] of the TOML file), e.g. torque_limit_nm=200",
    )
    p.add_argument("--iterations", type=int, help=f"number of trials, 1..{MAX_ITERATIONS} (default 10)")
    p.add_argument("--path", help="1-4 or a path TOML file (default 1)")
    p.add_argument("--cycle", type=float, dest="cycle_s", help="single-journey time in s (default 0.25)")
    p.add_argument("--profile", help=f"motion law: {', '.join(PROFILES)} (default ruckig)")
    p.add_argument("--disturbance", help=f"{_DISTURBANCE_HELP} (default none)")
    p.add_argument("--seed", type=int, help="seed of every random generator (default 0)")
    p.add_argument("--ff0", help="initial feed-forward: model | zero (default model)")
    p.add_argument("--gains", dest="preset", help=f"gain preset: {', '.join(GAIN_PRESET_NAMES)} (default normalized)")
    for name, hlp in (
        ("alpha", "α of the paper's law (feedback Kp = (α−1)Lp)"),
        ("beta", "β of the paper's law (feedback Kd = (β−1)Ld)"),
        ("lp", "learning P gain, N·m/rad (overrides lp_norm)"),
        ("ld", "learning D gain, N·m·s/rad (overrides ld_norm)"),
        ("lp-norm", "Lp·Ts²/I_joint"),
        ("ld-norm", "Ld·Ts/I_joint"),
        ("q-cutoff-hz", "Q-filter cut-off of q-ilc, Hz"),
        ("pdq-cutoff-hz", "Q-filter cut-off of pd-ilc-q, Hz"),
    ):
        p.add_argument(f"--{name}", type=float, dest=f"g_{name.replace('-', '_')}", help=hlp)
    p.add_argument("--lead", type=int, dest="g_lead", help="learning lead in samples (default 1)")
    p.add_argument(
        "--ff-transport",
        dest="ff_transport",
        help="feed-forward transport: table (SDO tables before each trial) | pdo (CiA 402 CSP, "
        "SYNC + RPDO/TPDO every tick) (default table)",
    )
    p.add_argument(
        "--fieldbus-bitrate",
        type=int,
        dest="fieldbus_bitrate",
        help="fieldbus bit rate in bit/s for the bus-fit check (default 1000000)",
    )
    p.add_argument(
        "--force-bus-fit",
        action="store_true",
        default=None,
        dest="force_bus_fit",
        help="run a pdo configuration even if its cyclic frames do not fit the fieldbus",
    )
    for name, what in (
        ("inertia", "rotational inertias"),
        ("mass", "link and platform masses"),
        ("friction", "Coulomb and viscous friction"),
        ("payload", "payload"),
    ):
        p.add_argument(
            f"--{name}-scale",
            type=float,
            dest=f"p_{name}_scale",
            metavar="FACTOR",
            help=f"plant uncertainty: the emulated robot's {what} times FACTOR ([plant] {name}_scale, default 1)",
        )
    p.add_argument("--out", default=None, help="run folder (default runs/<mode>-<time>)")


def experiment_actions() -> list[argparse.Action]:
    """The argparse actions of the experiment options, without ``--out`` (for the launcher)."""
    parser = argparse.ArgumentParser(add_help=False)
    add_experiment_args(parser)
    return [a for a in parser._actions if a.option_strings and a.dest not in NOT_EXPERIMENT]


def experiment_config(args: argparse.Namespace) -> ExperimentConfig:
    """The validated configuration of parsed experiment options (a ``--config`` file below them).

    :raises ValueError: one-line message naming the option or file.
    """
    from host.experiment.config import build_config  # heavy (plant, learning): only when needed

    overrides: dict[str, Any] = {
        k: getattr(args, k)
        for k in (
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
    }
    if getattr(args, "law_options", None) is not None:
        overrides["law_options"] = parse_law_options(args.law_options)
    gains: dict[str, Any] = {}  # merged over the file's [gains] table by build_config
    if args.preset is not None:
        gains["preset"] = args.preset
    for k, v in vars(args).items():
        if k.startswith("g_") and v is not None:
            gains[k[2:]] = v
    if gains:
        overrides["gains"] = gains
    plant = {k[2:]: v for k, v in vars(args).items() if k.startswith("p_") and k.endswith("_scale") and v is not None}
    if plant:
        overrides["plant"] = plant  # merged over the file's [plant] table
    return build_config(args.config, overrides)


def parse_law_options(text: str) -> dict[str, Any]:
    """``--law-options KEY=VALUE,KEY=VALUE``: values as in TOML (numbers, true/false, strings with or
    without quotes).

    :raises ValueError: one line naming the option.
    """
    import tomllib

    out: dict[str, Any] = {}
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        key, eq, raw = item.partition("=")
        key, raw = key.strip(), raw.strip()
        if not eq or not key or not raw:
            raise ValueError(f"--law-options {text!r}: expected KEY=VALUE[,KEY=VALUE…], got {item!r}")
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

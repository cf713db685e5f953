"""The ``ilcrig`` command line.

Subcommands:

* ``sim``   — a whole experiment in one process (no bus);
* ``run``   — the distributed rig: launches the bus hub (if the transport needs one), the plant,
  four drives and the host as separate processes, and cleans every one of them up;
* ``drive``, ``plant``, ``host``, ``hub`` — one role each, to run the parts in separate terminals
  (or machines, over a transport that spans them).
  Errors in the input are reported as
one line ``ilcrig: error: …`` with exit code 2 before anything moves; ``--debug`` shows
tracebacks.  A fault during a trial ends the run with exit code 3 after the summary (with every
completed trial) has been written.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import Any, Sequence

__all__ = ["main"]

logger = logging.getLogger(__name__)

EXIT_USAGE = 2
EXIT_FAULT = 3


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage dump) and exit code 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        sys.stderr.write(f"ilcrig: error: {message}\n")
        raise SystemExit(EXIT_USAGE)


def _add_experiment_args(p: argparse.ArgumentParser) -> None:
    from host.names import DISTURBANCES, GAIN_PRESET_NAMES, LAWS, PROFILES

    p.add_argument("--config", metavar="TOML", help="experiment file (keys as the options; unknown keys are errors)")
    p.add_argument("--law", help=f"learning law: {', '.join(LAWS)} (default pd-ilc)")
    p.add_argument("--iterations", type=int, help="number of trials (default 10)")
    p.add_argument("--path", help="1-4 or a path TOML file (default 1)")
    p.add_argument("--cycle", type=float, dest="cycle_s", help="single-journey time in s (default 0.25)")
    p.add_argument("--profile", help=f"motion law: {', '.join(PROFILES)} (default ruckig)")
    p.add_argument("--disturbance", help=f"{', '.join(DISTURBANCES)} (default none)")
    p.add_argument("--seed", type=int, help="seed of every random generator (default 0)")
    p.add_argument("--ff0", help="initial feed-forward: model | zero (default model)")
    p.add_argument("--gains", dest="preset", help=f"gain preset: {', '.join(GAIN_PRESET_NAMES)} (default normalized)")
    for name, hlp in (("alpha", "α of the paper's law (feedback Kp = (α−1)Lp)"),
                      ("beta", "β of the paper's law (feedback Kd = (β−1)Ld)"),
                      ("lp", "learning P gain, N·m/rad (overrides lp_norm)"),
                      ("ld", "learning D gain, N·m·s/rad (overrides ld_norm)"),
                      ("lp-norm", "Lp·Ts²/I_joint"), ("ld-norm", "Ld·Ts/I_joint"),
                      ("q-cutoff-hz", "Q-filter cut-off of q-ilc, Hz")):
        p.add_argument(f"--{name}", type=float, dest=f"g_{name.replace('-', '_')}", help=hlp)
    p.add_argument("--lead", type=int, dest="g_lead", help="learning lead in samples (default 1)")
    p.add_argument("--out", default=None, help="run folder (default runs/<mode>-<time>)")


def _experiment_config(args: argparse.Namespace):  # -> ExperimentConfig
    from host.config import build_config

    overrides: dict[str, Any] = {k: getattr(args, k) for k in (
        "law", "iterations", "path", "cycle_s", "profile", "disturbance", "seed", "ff0")}
    gains: dict[str, Any] = {}
    import tomllib

    if args.config:
        try:
            with open(args.config, "rb") as fh:
                gains = dict(tomllib.load(fh).get("gains", {}))
        except (OSError, tomllib.TOMLDecodeError):
            gains = {}  # build_config reports the file problem
    if args.preset is not None:
        gains["preset"] = args.preset
    for k, v in vars(args).items():
        if k.startswith("g_") and v is not None:
            gains[k[2:]] = v
    if gains:
        overrides["gains"] = gains
    return build_config(args.config, overrides)


def _print_header(stream) -> None:
    cols = "  ".join(f"RMSE j{j}" for j in range(1, 5)) + "  " + "  ".join(f"MaxE j{j}" for j in range(1, 5))
    stream.write(f"{'iter':>4}  {cols}   [deg]\n")


def _print_row(stream, m) -> None:
    vals = "  ".join(f"{v:7.5f}" for v in m.rmse_deg) + "  " + "  ".join(f"{v:7.5f}" for v in m.max_abs_deg)
    stream.write(f"{m.k:>4}  {vals}\n")
    stream.flush()


def cmd_sim(args: argparse.Namespace) -> int:
    from host.compose import InProcessBench
    from host.experiment import prepare, run_experiment

    cfg = _experiment_config(args)
    out = Path(args.out) if args.out else Path("runs") / time.strftime("sim-%Y%m%d-%H%M%S")
    plan = prepare(cfg)
    c = plan.check
    sys.stdout.write(
        f"ilcrig sim: law {cfg.law}, path {cfg.path}, cycle {cfg.cycle_s} s, profile {cfg.profile}, "
        f"disturbance {cfg.disturbance}, {cfg.iterations} iterations, N = {plan.n_ticks} ticks/trial\n"
        f"convergence check: spectral radius {c.rho_max:.4f} ({'ok' if c.ok else 'VIOLATED: expect divergence'}), "
        f"2-norm {c.norm2:.3f} ({'monotonic' if c.norm2 < 1 else 'not monotonic'}), paper eq.(18) rho {c.paper_rho18:.3f}; "
        f"predicted error ratio after {c.iterations} trials {c.predicted_ratio:.3g}, after {c.long_horizon} "
        f"{c.predicted_ratio_long:.3g}{' (diverges if run longer)' if c.predicted_ratio_long > 1 else ''}\n")
    _print_header(sys.stdout)
    bench = InProcessBench(cfg)
    from host.recording import RunRecorder

    recorder = RunRecorder(out / "recording.rrd", recording_id=out.name, config_summary=cfg.as_dict())
    res = run_experiment(plan, bench, out, mode="sim", on_trial=lambda m: _print_row(sys.stdout, m),
                         recorder=recorder)
    s = res.summary
    if s["iterations"]:
        from host.report import write_run_report

        write_run_report(out, s)  # report.md + convergence plot next to the summary
    sys.stdout.write(f"{s['ticks']} ticks in {s['wall_s']:.2f} s ({s['ticks_per_s']:.0f} ticks/s); "
                     f"trace_sha256 {s['trace_sha256'][:16]}…; summary: {out / 'summary.json'}\n")
    if res.fault:
        sys.stderr.write(f"ilcrig: fault: {res.fault} (torque removed; {len(s['iterations'])} trials kept)\n")
        return EXIT_FAULT
    return 0


def _add_bus_args(p: argparse.ArgumentParser, default: str = "auto") -> None:
    p.add_argument("--bus", default=default, metavar="TRANSPORT",
                   help="auto | hub | socketcan | udp_multicast | can_config (default %(default)s; auto = "
                        "socketcan on vcan0/vcan1 when they exist, else the zero-privilege hub)")
    p.add_argument("--hub", default=None, metavar="ADDRESS",
                   help="hub address, unix:/path or tcp:127.0.0.1:PORT (default: $ILCRIG_HUB or a per-user socket)")


def transport_of(args: argparse.Namespace):  # -> bus.transport.TransportConfig
    from bus.transport import transport_from_name

    return transport_from_name(args.bus, args.hub)


def cmd_drive(args: argparse.Namespace) -> int:
    from bus.transport import resolve_bus_config
    from firmware_model.node import run_node

    tc = transport_of(args)
    if not 1 <= args.node <= 127:
        raise ValueError(f"node id must be 1..127, got {args.node}")
    run_node(args.node, resolve_bus_config(tc.fieldbus), resolve_bus_config(tc.io))
    return 0


def cmd_plant(args: argparse.Namespace) -> int:
    from host.compose import run_plant_role

    run_plant_role(transport_of(args), node_id=args.node_id)
    return 0


def cmd_hub(args: argparse.Namespace) -> int:
    from bus.hub import main as hub_main

    return int(hub_main([x for a in (args.listen or []) for x in ("--listen", a)]) or 0)


def cmd_host(args: argparse.Namespace) -> int:
    from host.rig import run_host_role

    return run_host_role(args, _experiment_config(args), transport_of(args))


def cmd_run(args: argparse.Namespace) -> int:
    from host.launcher import launch_rig

    cfg = _experiment_config(args)  # validate before anything starts
    del cfg
    return launch_rig(args)


def cmd_view(args: argparse.Namespace) -> int:
    from host.recording import view_run

    return int(view_run(Path(args.run_dir)))


def cmd_reproduce(args: argparse.Namespace) -> int:
    from host.reproduce import reproduce_main

    return int(reproduce_main(args))


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="ilcrig", description="ILC on an emulated 4-DOF parallel robot with CAN servo drives")
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sp = sub.add_parser("sim", help="run an experiment in one process (no bus)")
    _add_experiment_args(sp)
    sp.set_defaults(func=cmd_sim)

    rp = sub.add_parser("run", help="run an experiment on the distributed rig (6 processes over CAN)")
    _add_experiment_args(rp)
    _add_bus_args(rp)
    rp.set_defaults(func=cmd_run)

    hp = sub.add_parser("host", help="the host role alone (expects 4 drives and the plant on the bus)")
    _add_experiment_args(hp)
    _add_bus_args(hp)
    hp.add_argument("--wait", type=float, default=120.0,
                    help="seconds to wait for the nodes to answer (default 120: a first run compiles the numba kernels)")
    hp.add_argument("--pause", type=float, default=0.0,
                    help="seconds to pause between trials (e.g. to restart a drive; a rebooted drive is set up again)")
    hp.set_defaults(func=cmd_host)

    dp = sub.add_parser("drive", help="one servo-drive node (firmware) on the bus")
    dp.add_argument("--node", type=int, required=True, help="CANopen node id (1-4 for the robot's joints)")
    _add_bus_args(dp)
    dp.set_defaults(func=cmd_drive)

    pp = sub.add_parser("plant", help="the plant (robot simulator) as the test-bench node on the bus")
    pp.add_argument("--node-id", type=int, default=32, help="CANopen node id of the test-bench node (default 32)")
    _add_bus_args(pp)
    pp.set_defaults(func=cmd_plant)

    vp = sub.add_parser("view", help="open a run's recording.rrd in the Rerun viewer (or print how to)")
    vp.add_argument("run_dir", help="a run folder (with recording.rrd)")
    vp.set_defaults(func=cmd_view)

    xp = sub.add_parser("reproduce", help="run the paper's experiments (Tables 2-6, Figs. 8 and 10) and beyond")
    xp.add_argument("--out", default="runs/reproduce", help="sweep folder (default runs/reproduce); reused to resume")
    xp.add_argument("--jobs", type=int, default=None, help="parallel processes (default: number of cores)")
    xp.add_argument("--iterations", type=int, default=10, help="trials per experiment (default 10)")
    xp.add_argument("--only", default=None, help="comma-separated subset: table2,table3,table4,table5,table6,figs,beyond")
    xp.add_argument("--fresh", action="store_true", help="ignore finished experiments in --out and redo all")
    xp.set_defaults(func=cmd_reproduce)

    bp = sub.add_parser("hub", help="the zero-privilege CAN hub (loopback / Unix socket only)")
    bp.add_argument("--listen", action="append", help="unix:/path or tcp:127.0.0.1:PORT (repeatable)")
    bp.set_defaults(func=cmd_hub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.debug else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        sys.stderr.write("ilcrig: interrupted\n")
        return 130
    except (ValueError, FileNotFoundError) as exc:
        if args.debug:
            raise
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        sys.stderr.write(f"ilcrig: error: {msg}\n")
        return EXIT_USAGE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

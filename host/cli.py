"""The ``ilcrig`` command line.

Subcommands:

* ``sim``   — a whole experiment in one process (no bus), run through the public API :mod:`ilcrig`;
* ``laws``  — the learning laws this installation knows (built-in and plug-ins);
* ``sweep`` — a grid and/or Monte Carlo draws of experiments on Dask distributed, ``tune`` — gains
  tuned with Optuna on the same engine, ``reproduce`` — the paper's experiments as a predefined
  sweep (their options and handlers: :mod:`host.studies.commands`);
* ``run``   — the distributed rig: launches the bus hub (if the transport needs one), the plant,
  four drives and the host as separate processes, and cleans every one of them up;
* ``robot`` — the drives and the plant as a robot on the bus, without the ILC host, for any CANopen
  master (:mod:`host.rig.robot_launcher`, docs/robot.md);
* ``view`` — a run's ``recording.rrd`` in the Rerun viewer (:func:`host.analysis.viewer.view_run`);
* ``drive``, ``plant``, ``host``, ``hub`` — one role each, to run the parts in separate terminals
  (or machines, over a transport that spans them).

Errors in the input are reported as one line ``ilcrig: error: …`` with exit code 2 before anything moves; ``--debug`` shows
tracebacks.  A fault during a trial ends the run with exit code 3 after the summary (with every
completed trial) has been written.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from bus.exit_codes import EXIT_FAULT, EXIT_INTERRUPTED, EXIT_USAGE
from bus.plant_objects import DEFAULT_PLANT_NODE_ID
from host.experiment.console import add_experiment_args, experiment_config
from host.rig.realtime import DEFAULT_RT_PRIORITY

__all__ = ["main"]

if TYPE_CHECKING:
    from bus.transports.config import TransportConfig

logger = logging.getLogger(__name__)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage dump) and exit code 2."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"ilcrig: error: {message}\n")
        raise SystemExit(EXIT_USAGE)


def cmd_sim(args: argparse.Namespace) -> int:
    """``ilcrig sim``: the experiment in this process, through the public API (:mod:`ilcrig`)."""
    from host.experiment.outputs import check_out_dir

    out = Path(args.out) if args.out is not None else Path("runs") / time.strftime("sim-%Y%m%d-%H%M%S")
    check_out_dir(args.out if args.out is not None else out, create=False)  # fast: before the configuration
    cfg = experiment_config(args)
    check_out_dir(out, iterations=cfg.iterations, n_ticks=cfg.n_ticks, create=False)
    import ilcrig
    from host.analysis.session import report_fault
    from host.experiment.signal_shield import interrupt_on_signals

    exp = ilcrig.Experiment.from_config(cfg)
    exp.plan  # noqa: B018 - prepared (and refused with one line) before the run folder is made
    session = exp.start(out, stream=sys.stdout, view=bool(args.view))
    with interrupt_on_signals():
        for _ in session:
            pass
    session.close()
    res = session.raw
    s = res.summary
    sys.stdout.write(
        f"{s['ticks']} ticks in {s['wall_s']:.2f} s ({s['ticks_per_s']:.0f} ticks/s); "
        f"trace_sha256 {s['trace_sha256'][:16]}…; summary: {out / 'summary.json'}\n"
    )
    return report_fault(res, out / "summary.json")


def _add_bus_args(p: argparse.ArgumentParser, default: str = "auto") -> None:
    p.add_argument(
        "--bus",
        default=default,
        metavar="TRANSPORT",
        help="auto | hub | socketcan | udp_multicast | can_config (default %(default)s; auto = "
        "socketcan on vcan0/vcan1 when they exist, else the zero-privilege hub)",
    )
    p.add_argument(
        "--hub",
        default=None,
        metavar="ADDRESS",
        help="hub address, unix:/path or tcp:127.0.0.1:PORT (default: $ILCRIG_HUB or hub.sock in this user's "
        "private folder, $XDG_RUNTIME_DIR/ilcrig or $TMPDIR/ilcrig-<uid>)",
    )
    p.add_argument(
        "--allow-remote",
        action="store_true",
        help="the hub may be on another machine (a non-loopback tcp: address); off by default",
    )


def _add_rig_args(p: argparse.ArgumentParser) -> None:
    """Options of the rig that do not change the experiment (its results and digest)."""
    p.add_argument(
        "--realtime",
        action="store_true",
        help="pace the plant's ticks to the wall clock at the control period (tick n starts at t0 + n·Ts) "
        "and report deadline misses and tick lateness",
    )
    p.add_argument(
        "--rt-priority",
        type=_rt_priority,
        default=None,
        metavar="N",
        help="with --realtime: the SCHED_FIFO priority of the hub, plant and drive processes, 1..99 "
        f"(default {DEFAULT_RT_PRIORITY}; 0 = normal scheduling); without the right to it "
        "(CAP_SYS_NICE or RLIMIT_RTPRIO) the run uses normal scheduling and says so",
    )
    p.add_argument(
        "--no-idle-poll",
        action="store_true",
        help="with --realtime: let idle CPUs halt (by default a SCHED_IDLE busy loop per CPU keeps them "
        "awake for the run, so no wake-up of a tick waits for a halted CPU; it uses only CPU time "
        "nothing else wants)",
    )
    # the fieldbus bit rate is an experiment option (--fieldbus-bitrate: also the pdo bus-fit check)
    p.add_argument(
        "--io-bitrate",
        type=_bitrate,
        default=None,
        metavar="BIT_S",
        help="bit rate of the io channel for the bus-time figures (default 1000000)",
    )
    _add_view_arg(p)
    p.add_argument(
        "--bus-time",
        action="store_true",
        help="the hub carries both channels in bus time at their bit rates (--io-bitrate, "
        "--fieldbus-bitrate): frames in arbitration order, each delivered after its bit time, so "
        "transfers take as long as on a real bus (hub transport only)",
    )


def _add_view_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--view",
        action="store_true",
        help="stream to a Rerun viewer as it happens: the viewer opens when there is a display, otherwise the "
        "stream is served on 127.0.0.1 and the command that connects a viewer is printed",
    )


def _rt_priority(text: str) -> int:
    """``--rt-priority``: 0..99 (0 = normal scheduling)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer 0..99, got {text!r}") from None
    if not 0 <= value <= 99:
        raise argparse.ArgumentTypeError(f"must be 0..99 (0 = normal scheduling), got {value}")
    return value


def _bitrate(text: str) -> int:
    """A bit rate option: a positive integer, bit/s."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"bit rate must be an integer in bit/s, got {text!r}") from None
    if not 1000 <= value <= 1_000_000:
        raise argparse.ArgumentTypeError(f"a classic CAN bit rate is 1000..1000000 bit/s, got {value}")
    return value


def transport_of(args: argparse.Namespace) -> TransportConfig:
    from bus.transports.config import transport_from_name

    return transport_from_name(args.bus, args.hub, bool(getattr(args, "allow_remote", False)))


def cmd_drive(args: argparse.Namespace) -> int:
    from bus.transports.config import resolve_bus_config
    from firmware_model.drive_node import run_node

    tc = transport_of(args)
    if not 1 <= args.node <= 127:
        raise ValueError(f"node id must be 1..127, got {args.node}")
    _role_logging()
    with _bus_errors(tc.name):
        lost = run_node(
            args.node,
            resolve_bus_config(tc.fieldbus),
            resolve_bus_config(tc.io),
            param_dir=args.param_dir,
            lockstep=args.lockstep,
        )
    return EXIT_FAULT if lost else 0


def cmd_plant(args: argparse.Namespace) -> int:
    from bus.plant_objects import RobotMode
    from plant.plant_node import run_plant_role

    _role_logging()
    mode = {None: RobotMode.OFF, "sync": RobotMode.SYNC, "realtime": RobotMode.REALTIME}[args.robot]
    tc = transport_of(args)
    with _bus_errors(tc.name):
        lost = run_plant_role(tc, node_id=args.node_id, robot_mode=mode, trace_path=args.trace, summary_path=args.summary)
    return EXIT_FAULT if lost else 0


class _BusUnavailable(Exception):
    """A role could not open its bus (reported as ``ilcrig: error: cannot open the bus …``, exit 3)."""


@contextlib.contextmanager
def _bus_errors(transport: str) -> Iterator[None]:
    """A bus a role cannot open (nobody listens, …) as one line, like the host role's."""
    import can

    try:
        yield
    except can.CanInitializationError as exc:
        raise _BusUnavailable(f"cannot open the bus ({transport}): {exc}") from exc


def _role_logging() -> None:
    """Node roles log the project's INFO records too (their SAFE-STATE records, NMT, trials) with
    a time stamp: their output is a log file of ``ilcrig run``."""
    root = logging.getLogger()
    for handler in root.handlers:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    for name in ("bus", "firmware_model", "plant"):
        logging.getLogger(name).setLevel(min(logging.INFO, root.level))


def cmd_hub(args: argparse.Namespace) -> int:
    from bus.transports.hub.cli import main as hub_main

    argv = [x for a in (args.listen or []) for x in ("--listen", a)]
    return int(hub_main(argv + (["--allow-remote"] if args.allow_remote else [])) or 0)


def cmd_host(args: argparse.Namespace) -> int:
    from host.rig.host_role import run_host_role

    return run_host_role(args, experiment_config(args), transport_of(args))


def cmd_run(args: argparse.Namespace) -> int:
    from host.rig.launcher import launch_rig
    from host.rig.options import RunOptions

    return launch_rig(RunOptions.from_args(args))  # validates everything (preflight) before anything starts


def cmd_robot(args: argparse.Namespace) -> int:
    from host.rig.options import RobotOptions
    from host.rig.robot_launcher import launch_robot

    return launch_robot(RobotOptions.from_args(args))


def cmd_laws(args: argparse.Namespace) -> int:
    """``ilcrig laws``: every law name this installation knows, with its one-line description."""
    import ilcrig

    laws = ilcrig.available_laws()
    width = max(len(n) for n in laws)
    for name, text in laws.items():
        sys.stdout.write(f"{name:<{width}}  {text}\n")
    sys.stdout.write(f"(plug-ins: entry-point group {ilcrig.ENTRY_POINT_GROUP}; any law also as --law module:Class)\n")
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from host.analysis.viewer import view_run

    return int(view_run(Path(args.run_dir)))


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="ilcrig", description="ILC on an emulated 4-DOF parallel robot with CAN servo drives")
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sp = sub.add_parser("sim", help="run an experiment in one process (no bus)")
    add_experiment_args(sp)
    _add_view_arg(sp)
    sp.set_defaults(func=cmd_sim)

    rp = sub.add_parser("run", help="run an experiment on the distributed rig (6 processes over CAN)")
    add_experiment_args(rp)
    _add_bus_args(rp)
    _add_rig_args(rp)
    rp.add_argument(
        "--inject",
        action="append",
        metavar="SPEC",
        help="inject a fault (repeatable): kill|stall:ROLE@WHEN[,for=S], "
        "drop|corrupt|duplicate|delay:io|fieldbus@WHEN[,rate=P,seed=K,count=C,id=COBID,ms=D], "
        "emcy:NODE@WHEN[,code=C], diskfull@WHEN; WHEN = TRIAL:TICK, TRIAL:end, before or after "
        "(docs/faults.md: Fault injection)",
    )
    rp.set_defaults(func=cmd_run)

    op = sub.add_parser(
        "robot", help="the four drives and the plant as a robot on the bus, for any CANopen master (docs/robot.md)"
    )
    _add_bus_args(op)
    op.add_argument("--out", default=None, metavar="DIR", help="run folder (default runs/robot-<time>)")
    op.add_argument(
        "--realtime",
        action="store_true",
        help="pace the robot's periods to the wall clock (period n not before t0 + n·Ts) and count late and missing SYNCs",
    )
    op.add_argument(
        "--rt-priority",
        type=_rt_priority,
        default=None,
        metavar="N",
        help=f"with --realtime: SCHED_FIFO priority of the hub, plant and drives, 1..99 "
        f"(default {DEFAULT_RT_PRIORITY}; 0 = normal)",
    )
    op.add_argument("--no-idle-poll", action="store_true", help="with --realtime: let idle CPUs halt")
    op.add_argument(
        "--param-dir",
        default=None,
        metavar="DIR",
        help="folder where the drives keep the parameters a master saves with 0x1010 (default: in memory, one session)",
    )
    _add_view_arg(op)
    op.set_defaults(func=cmd_robot)

    hp = sub.add_parser("host", help="the host role alone (expects 4 drives and the plant on the bus)")
    add_experiment_args(hp)
    _add_bus_args(hp)
    _add_rig_args(hp)
    hp.add_argument("--rt-scheduling", default=None, help=argparse.SUPPRESS)  # the launcher's: what --realtime got
    hp.add_argument(
        "--wait",
        type=float,
        default=120.0,
        help="seconds to wait for the nodes to answer (default 120: a first run compiles the numba kernels)",
    )
    hp.add_argument(
        "--pause", type=float, default=0.0, help="seconds to pause between trials (e.g. to restart a drive, with --recover)"
    )
    hp.add_argument(
        "--recover",
        type=float,
        default=0.0,
        help="> 0: a node lost or rebooted between trials is waited for (up to --wait) and set up again "
        "instead of ending the run (default 0: every lost node is a fault)",
    )
    hp.add_argument("--inject-disk-full", default=None, metavar="SPEC", help=argparse.SUPPRESS)  # the launcher's diskfull@…
    hp.set_defaults(func=cmd_host)

    dp = sub.add_parser("drive", help="one servo-drive node (firmware) on the bus")
    dp.add_argument("--node", type=int, required=True, help="CANopen node id (1-4 for the robot's joints)")
    dp.add_argument(
        "--param-dir",
        default=None,
        metavar="DIR",
        help="folder of the parameters 0x1010 saves (node<id>.json; default: in memory)",
    )
    dp.add_argument(
        "--lockstep",
        action="store_true",
        help="a drive of a SYNC-stepped plant (ilcrig robot): a SYNC's TPDOs carry its control cycle, "
        "the PDO timers count control periods (docs/robot.md)",
    )
    _add_bus_args(dp)
    dp.set_defaults(func=cmd_drive)

    pp = sub.add_parser("plant", help="the plant (robot simulator) as the plant node on the bus")
    pp.add_argument(
        "--node-id", type=int, default=DEFAULT_PLANT_NODE_ID, help="CANopen node id of the plant node (default %(default)s)"
    )
    pp.add_argument(
        "--robot",
        choices=("sync", "realtime"),
        default=None,
        help="start as the robot (docs/robot.md): one control period per SYNC (sync), also paced to the wall clock (realtime)",
    )
    pp.add_argument("--trace", default=None, metavar="FILE", help="with --robot: write the period trace here")
    pp.add_argument("--summary", default=None, metavar="FILE", help="write the node's counters as JSON here on exit")
    _add_bus_args(pp)
    pp.set_defaults(func=cmd_plant)

    lp = sub.add_parser("laws", help="list the learning laws: built-in, plug-ins (entry points ilcrig.laws)")
    lp.set_defaults(func=cmd_laws)

    vp = sub.add_parser("view", help="open a run's recording.rrd in the Rerun viewer (or print how to)")
    vp.add_argument("run_dir", help="a run folder (with recording.rrd)")
    vp.set_defaults(func=cmd_view)

    from host.studies.commands import add_reproduce_parser, add_sweep_parser, add_tune_parser

    add_reproduce_parser(sub)
    add_sweep_parser(sub)
    add_tune_parser(sub)

    bp = sub.add_parser("hub", help="the zero-privilege CAN hub (loopback / Unix socket unless --allow-remote)")
    bp.add_argument("--listen", action="append", help="unix:/path or tcp:127.0.0.1:PORT (repeatable)")
    bp.add_argument(
        "--allow-remote",
        action="store_true",
        help="also accept a non-loopback tcp:ADDRESS:PORT, to serve roles on other machines",
    )
    bp.set_defaults(func=cmd_hub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.debug else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        sys.stderr.write("ilcrig: interrupted\n")
        return EXIT_INTERRUPTED
    except _BusUnavailable as exc:
        sys.stderr.write(f"ilcrig: error: {exc}\n")
        return EXIT_FAULT
    except (ValueError, FileNotFoundError) as exc:
        if args.debug:
            raise
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        sys.stderr.write(f"ilcrig: error: {msg}\n")
        return EXIT_USAGE
    except Exception as exc:  # noqa: BLE001 - one line, never a traceback on the terminal
        if args.debug:
            raise
        logger.debug("unexpected error", exc_info=True)
        msg = str(exc).splitlines()[0] if str(exc) else ""
        sys.stderr.write(f"ilcrig: internal error: {type(exc).__name__}: {msg} (run with --debug for details)\n")
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

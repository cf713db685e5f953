"""The option groups several ``ilcrig`` commands share, each defined once.

This module owns the experiment options' parser (:func:`add_experiment_args`, built from
:data:`host.experiment.console.EXPERIMENT_OPTIONS`, with ``--out``), the bus options (``--bus``,
``--hub``, ``--allow-remote``: :func:`add_bus_args`, their :class:`BusOptions` and
:func:`transport_of`), the real-time options (``--realtime``, ``--rt-priority``,
``--no-idle-poll``: :func:`add_realtime_args`, used by ``run``, ``host`` and ``robot``), the rig
options that do not change the experiment (:func:`add_rig_args`: the real-time options,
``--io-bitrate``, ``--view``, ``--bus-time``, ``--firmware``), ``--view`` (:func:`add_view_arg`),
``--firmware`` (:func:`add_firmware_arg`: the drives' firmware, checked at parse time), the option
value types (:func:`rt_priority`, :func:`bitrate`, :func:`firmware`), what every node role does around
its loop (:func:`role_logging`, :func:`bus_errors`), and the typed options the parsed groups become
(:func:`options_of`, :func:`experiment_options`: nothing below the command line gets a Namespace).

May import: what ``host.cli`` may (it is part of it); kept import-light: every role parses the
command line.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

from host.experiment.console import EXPERIMENT_OPTIONS, ExperimentOptions
from host.rig.realtime import DEFAULT_RT_PRIORITY

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

    from bus.transports.config import TransportConfig

_Options = TypeVar("_Options", bound="DataclassInstance")

__all__ = [
    "BusOptions",
    "BusUnavailable",
    "add_bus_args",
    "add_experiment_args",
    "add_firmware_arg",
    "add_realtime_args",
    "add_rig_experiment_args",
    "add_rig_args",
    "add_view_arg",
    "bitrate",
    "bus_errors",
    "bus_options",
    "experiment_options",
    "options_of",
    "firmware",
    "role_logging",
    "rt_priority",
    "transport_of",
]


@dataclass(frozen=True)
class BusOptions:
    """``--bus``, ``--hub``, ``--allow-remote``: which transport carries the channels."""

    bus: str = "auto"
    hub: str | None = None
    allow_remote: bool = False

    def transport(self) -> TransportConfig:
        """The transport configuration (:class:`bus.errors.InputError` for a bad name or address)."""
        from bus.transports.config import transport_from_name

        return transport_from_name(self.bus, self.hub, self.allow_remote)


def bus_options(args: argparse.Namespace) -> BusOptions:
    """The parsed bus options of a command."""
    return BusOptions(args.bus, args.hub, bool(getattr(args, "allow_remote", False)))


def transport_of(args: argparse.Namespace) -> TransportConfig:
    """The transport of a command's parsed bus options."""
    return bus_options(args).transport()


def add_experiment_args(p: argparse.ArgumentParser) -> None:
    """The experiment options (``--law``, ``--iterations``, …) and the run folder ``--out`` on ``p``."""
    for o in EXPERIMENT_OPTIONS:
        if o.switch:
            p.add_argument(o.flag, action="store_true", default=None, dest=o.dest, help=o.help)
        else:
            p.add_argument(o.flag, dest=o.dest, type=o.type or str, metavar=o.metavar, help=o.help)
    p.add_argument("--out", default=None, help="run folder (default runs/<mode>-<time>)")


def add_rig_experiment_args(p: argparse.ArgumentParser) -> None:
    """An experiment on the rig: the experiment, bus and rig options — what ``run`` takes, and the
    host role too (the launcher passes them on to it)."""
    add_experiment_args(p)
    add_bus_args(p)
    add_rig_args(p)


def add_bus_args(p: argparse.ArgumentParser, default: str = "auto") -> None:
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


def add_realtime_args(p: argparse.ArgumentParser, paced: str) -> None:
    """``--realtime`` (what it paces: ``paced``), ``--rt-priority``, ``--no-idle-poll``."""
    p.add_argument("--realtime", action="store_true", help=paced)
    p.add_argument(
        "--rt-priority",
        type=rt_priority,
        default=None,
        metavar="N",
        help="with --realtime: the SCHED_FIFO priority of the hub, plant and drive processes, 1..99 "
        f"(default {DEFAULT_RT_PRIORITY}; 0 = normal scheduling); without the right to it "
        "(CAP_SYS_NICE or RLIMIT_RTPRIO) the run uses normal scheduling and says so",
    )
    p.add_argument(
        "--no-idle-poll",
        action="store_true",
        help="with --realtime: let idle CPUs halt (by default a SCHED_IDLE busy loop per CPU beside "
        "SCHED_FIFO, and where root a PM QoS CPU latency request of 0 us in either class, keep them "
        "awake for the run, so no wake-up of a tick waits for a halted CPU)",
    )


def add_rig_args(p: argparse.ArgumentParser) -> None:
    """Options of the rig that do not change the experiment (its results and digest)."""
    add_realtime_args(
        p,
        "pace the plant's ticks to the wall clock at the control period (tick n starts at t0 + n·Ts) "
        "and report deadline misses and tick lateness",
    )
    # the fieldbus bit rate is an experiment option (--fieldbus-bitrate: also the pdo bus-fit check)
    p.add_argument(
        "--io-bitrate",
        type=bitrate,
        default=None,
        metavar="BIT_S",
        help="bit rate of the io channel for the bus-time figures (default 1000000)",
    )
    add_view_arg(p)
    add_firmware_arg(p)
    p.add_argument(
        "--bus-time",
        action="store_true",
        help="the hub carries both channels in bus time at their bit rates (--io-bitrate, "
        "--fieldbus-bitrate): frames in arbitration order, each delivered after its bit time, so "
        "transfers take as long as on a real bus (hub transport only)",
    )


def add_view_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--view",
        action="store_true",
        help="stream to a Rerun viewer as it happens: the viewer opens when there is a display, otherwise the "
        "stream is served on 127.0.0.1 and the command that connects a viewer is printed",
    )


def add_firmware_arg(p: argparse.ArgumentParser) -> None:
    """``--firmware {python,c,pil}``: the implementation of the drives' control period (the results and
    the digest are the same with each; docs/firmware.md)."""
    from firmware_model.firmware_select import DEFAULT_FIRMWARE, FIRMWARES

    p.add_argument(
        "--firmware",
        type=firmware,
        default=DEFAULT_FIRMWARE,
        metavar="{" + ",".join(FIRMWARES) + "}",
        help="the drives' control period: python (the reference model), c (the C core, software in the loop), "
        "pil (processor in the loop) (default %(default)s; docs/firmware.md)",
    )


def firmware(text: str) -> str:
    """``--firmware``: one of :data:`firmware_model.firmware_select.FIRMWARES` that this installation can
    run (``c`` needs the built extension) -- checked when the command line is parsed, before any
    process starts."""
    from bus.errors import InputError
    from firmware_model.firmware_select import check_firmware

    try:
        return check_firmware(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--firmware: ")) from None  # argparse names it


def rt_priority(text: str) -> int:
    """``--rt-priority``: 0..99 (0 = normal scheduling)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer 0..99, got {text!r}") from None
    if not 0 <= value <= 99:
        raise argparse.ArgumentTypeError(f"must be 0..99 (0 = normal scheduling), got {value}")
    return value


def bitrate(text: str) -> int:
    """A bit rate option: a classic CAN bit rate, bit/s."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"bit rate must be an integer in bit/s, got {text!r}") from None
    if not 1000 <= value <= 1_000_000:
        raise argparse.ArgumentTypeError(f"a classic CAN bit rate is 1000..1000000 bit/s, got {value}")
    return value


class BusUnavailable(Exception):
    """A role could not open its bus (reported as ``ilcrig: error: cannot open the bus …``, exit 3)."""


@contextlib.contextmanager
def bus_errors(transport: str) -> Iterator[None]:
    """A bus a role cannot open (nobody listens, …) as one line, like the host role's."""
    import can

    try:
        yield
    except can.CanInitializationError as exc:
        raise BusUnavailable(f"cannot open the bus ({transport}): {exc}") from exc


#: the loggers whose INFO records a node role keeps (its SAFE-STATE records, NMT, trials)
NODE_INFO_LOGGERS = ("bus", "firmware_model", "plant")
#: the loggers whose INFO records the host role keeps: the decisions of its heartbeat consumer (a
#: silence excused by a carrier's wait for a CPU, heartbeats judged afresh after the host itself
#: did not run), which a lost node's fault must be read against
HOST_INFO_LOGGERS = ("bus.run_queue", "host.rig.watchdog")


def role_logging(info_from: tuple[str, ...] = NODE_INFO_LOGGERS) -> None:
    """A role's log records with a time stamp (its output is a log file of ``ilcrig run``, read
    beside the other roles'), and the INFO records of the loggers ``info_from`` too."""
    root = logging.getLogger()
    for handler in root.handlers:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    for name in info_from:
        logging.getLogger(name).setLevel(min(logging.INFO, root.level))


def experiment_options(args: argparse.Namespace) -> ExperimentOptions:
    """The typed experiment options of a command parsed with :func:`add_experiment_args`."""
    return ExperimentOptions.from_values(vars(args))


def options_of(cls: type[_Options], args: argparse.Namespace, **given: Any) -> _Options:
    """The typed options ``cls`` (a dataclass) of a parsed command line: each field the value of
    the option of its name, ``given`` for the fields whose option is named or formed otherwise (a
    field without either keeps its default)."""
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)}
    return cls(**(values | given))

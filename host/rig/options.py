"""The typed options of the two launchers: :class:`RunOptions` (``ilcrig run``) and
:class:`RobotOptions` (``ilcrig robot``), built once from the parsed command line.

This module owns what the launch code (:mod:`host.rig.launch_core`, :mod:`host.rig.launcher`,
:mod:`host.rig.robot_launcher`) may know of the command line: frozen dataclasses instead of an
``argparse.Namespace`` travelling into it.  The experiment options of ``ilcrig run`` stay the raw
option mapping (:attr:`RunOptions.experiment`): the host role gets them back as its own command
line (:func:`host.rig.role_commands.host_role_args`) and the configuration is built from them by
:func:`host.experiment.console.experiment_config` — both take a Namespace, which
:meth:`RunOptions.namespace` gives.

May import: the standard library only.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Self

__all__ = ["RigOptions", "RobotOptions", "RunOptions"]


@dataclass(frozen=True)
class RigOptions:
    """What both launchers take.

    :ivar bus: the transport name (``auto``, ``hub``, ``socketcan``, …)
    :ivar hub: the hub's address (``--hub``; None: a fresh private socket)
    :ivar out: the run folder (None: ``runs/<kind>-<time>``)
    :ivar realtime: ``--realtime``
    :ivar rt_priority: ``--rt-priority`` (None: the default, :data:`host.rig.realtime.DEFAULT_RT_PRIORITY`)
    :ivar no_idle_poll: ``--no-idle-poll``
    :ivar allow_remote: ``--allow-remote`` (a hub address off this machine)
    :ivar view: ``--view``
    :ivar debug: ``--debug``
    :ivar firmware: ``--firmware``, the drives' control-period implementation (``python``, ``c``, ``pil``)
    """

    bus: str = "auto"
    hub: str | None = None
    out: str | None = None
    realtime: bool = False
    rt_priority: int | None = None
    no_idle_poll: bool = False
    allow_remote: bool = False
    view: bool = False
    debug: bool = False
    firmware: str = "python"

    @classmethod
    def _common(cls, args: argparse.Namespace) -> dict[str, Any]:
        return {
            "bus": getattr(args, "bus", "auto"),
            "hub": getattr(args, "hub", None),
            "out": None if getattr(args, "out", None) is None else str(args.out),
            "realtime": bool(getattr(args, "realtime", False)),
            "rt_priority": getattr(args, "rt_priority", None),
            "no_idle_poll": bool(getattr(args, "no_idle_poll", False)),
            "allow_remote": bool(getattr(args, "allow_remote", False)),
            "view": bool(getattr(args, "view", False)),
            "debug": bool(getattr(args, "debug", False)),
            "firmware": str(getattr(args, "firmware", "python")),
        }


@dataclass(frozen=True)
class RunOptions(RigOptions):
    """``ilcrig run``'s options.

    :ivar inject: the ``--inject`` specs, as given
    :ivar bus_time: ``--bus-time``
    :ivar io_bitrate: ``--io-bitrate``, bit/s (None: the default)
    :ivar experiment: every parsed option of the command (the experiment's among them), as parsed
    """

    inject: tuple[str, ...] = ()
    bus_time: bool = False
    io_bitrate: int | None = None
    experiment: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Self:
        """The options of a parsed ``ilcrig run`` command line."""
        return cls(
            **cls._common(args),
            inject=tuple(getattr(args, "inject", None) or ()),
            bus_time=bool(getattr(args, "bus_time", False)),
            io_bitrate=getattr(args, "io_bitrate", None),
            experiment=dict(vars(args)),
        )

    def namespace(self) -> argparse.Namespace:
        """The parsed command line again (for :func:`host.experiment.console.experiment_config`
        and :func:`host.rig.role_commands.host_role_args`)."""
        return argparse.Namespace(**self.experiment)


@dataclass(frozen=True)
class RobotOptions(RigOptions):
    """``ilcrig robot``'s options.

    :ivar param_dir: ``--param-dir`` (None: the drives keep their parameters in memory)
    """

    param_dir: str | None = None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Self:
        """The options of a parsed ``ilcrig robot`` command line."""
        param_dir = getattr(args, "param_dir", None)
        return cls(**cls._common(args), param_dir=None if param_dir is None else str(param_dir))

"""The typed options of the two launchers: :class:`RunOptions` (``ilcrig run``) and
:class:`RobotOptions` (``ilcrig robot``), built once from the parsed command line.

This module owns what the launch code (:mod:`host.rig.launch_core`, :mod:`host.rig.launcher`,
:mod:`host.rig.robot_launcher`) may know of the command line: frozen dataclasses, built by the
command line (:mod:`host.cli.run`, :mod:`host.cli.robot`).  The experiment options of ``ilcrig run``
are the typed :class:`host.experiment.console.ExperimentOptions` (:attr:`RunOptions.experiment`):
the host role gets them back as its own command line
(:func:`host.rig.role_commands.host_role_args`) and the configuration is built from them by
:func:`host.experiment.console.experiment_config`.

May import: the standard library, :mod:`host.experiment.console` (import-light).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from host.experiment.console import ExperimentOptions

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


@dataclass(frozen=True)
class RunOptions(RigOptions):
    """``ilcrig run``'s options.

    :ivar inject: the ``--inject`` specs, as given
    :ivar bus_time: ``--bus-time``
    :ivar io_bitrate: ``--io-bitrate``, bit/s (None: the default)
    :ivar experiment: the experiment options given
    """

    inject: tuple[str, ...] = ()
    bus_time: bool = False
    io_bitrate: int | None = None
    experiment: ExperimentOptions = field(default_factory=ExperimentOptions)


@dataclass(frozen=True)
class RobotOptions(RigOptions):
    """``ilcrig robot``'s options.

    :ivar param_dir: ``--param-dir`` (None: the drives keep their parameters in memory)
    """

    param_dir: str | None = None

"""The command lines of the role processes of ``ilcrig run``.

This module owns how a role is started: ``[sys.executable, "-P", "-m", "host.cli", ROLE, ...]``
(:func:`role_command`). ``-P`` (Python's safe-path mode) keeps the folder ``ilcrig run`` was started
in off the role's import path, so a ``plant.py``, ``bus.py`` or ``host.py`` there cannot shadow the
project's packages; the installed packages (site-packages, the editable install) and
``PYTHONPATH`` still apply.  It also owns which options of ``ilcrig run`` go on to the host
(:func:`host_role_args`, :func:`rig_role_args`) and the hub's bus-time rates (:func:`bus_time_rates`).

Test hook
    The command of a role can be replaced, for tests with fake role scripts, by the module
    dict :data:`ROLE_COMMAND` (role → argv prefix) or by the environment variables
    ``ILCRIG_ROLE_CMD_<ROLE>`` (``HOST``, ``PLANT``, ``DRIVE``, and ``DRIVE1`` … ``DRIVE4`` for
    one drive; a shell-like string split with :func:`shlex.split`). The environment wins. The
    role's arguments (e.g. ``--node 2 --bus hub --hub unix:…``) are appended to the override.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from collections.abc import Sequence

from bus.busload import DEFAULT_BITRATE_BPS
from bus.transports.config import FIELDBUS
from bus.transports.config import IO as IO_CHANNEL
from host.experiment.console import EXPERIMENT_OPTIONS

__all__ = [
    "PYTHON_ROLE_FLAGS",
    "ROLE_COMMAND",
    "ROLE_ENV_PREFIX",
    "bus_time_rates",
    "child_argv",
    "host_role_args",
    "rig_role_args",
    "role_command",
]

#: the interpreter flags of every role: safe-path mode, the working folder is not importable
PYTHON_ROLE_FLAGS: tuple[str, ...] = ("-P",)
#: environment variable prefix of the role-command test hook
ROLE_ENV_PREFIX: str = "ILCRIG_ROLE_CMD_"
#: test hook: role name ("host", "plant", "drive", "drive1" …) → argv prefix replacing
#: ``[sys.executable, "-P", "-m", "host.cli", ROLE]``
ROLE_COMMAND: dict[str, list[str]] = {}


def role_command(role: str, node: int | None = None, *, debug: bool = False) -> list[str]:
    """argv prefix of ``role`` (``host``, ``plant``, ``drive``), honouring the test hooks.

    :param node: the drive's node id (selects ``ILCRIG_ROLE_CMD_DRIVE<node>`` first)
    :param debug: pass ``--debug`` to the real ``ilcrig`` command
    """
    keys = ([f"{role}{node}"] if node is not None else []) + [role]
    for key in keys:
        env = os.environ.get(ROLE_ENV_PREFIX + key.upper())
        if env:
            return shlex.split(env)
    for key in keys:
        if key in ROLE_COMMAND:
            return list(ROLE_COMMAND[key])
    return [sys.executable, *PYTHON_ROLE_FLAGS, "-m", "host.cli"] + (["--debug"] if debug else []) + [role]


def host_role_args(args: argparse.Namespace) -> list[str]:
    """The experiment options of ``args`` (a parsed ``run`` Namespace) as host-role arguments.

    Only options that were given (not ``None``) are passed; ``--out``, ``--bus`` and ``--hub``
    are added by the launcher. Floats keep their exact value (``repr`` round-trips).
    """
    argv: list[str] = []
    for option in EXPERIMENT_OPTIONS:
        value = getattr(args, option.dest, None)
        if value is None or value is False:
            continue
        if option.switch:
            argv.append(option.flag)
            continue
        argv += [option.flag, repr(value) if isinstance(value, float) else str(value)]
    return argv


def rig_role_args(args: argparse.Namespace) -> list[str]:
    """The rig options of ``args`` (``--realtime``, ``--view``, ``--bus-time``, ``--io-bitrate``, ``--firmware``) that the
    host role takes too (``--fieldbus-bitrate`` is an experiment option and goes with :func:`host_role_args`; the host
    records the drives' firmware in the summary)."""
    argv = ["--realtime"] if args.realtime else []
    if getattr(args, "view", False):
        argv.append("--view")
    if getattr(args, "bus_time", False):
        argv.append("--bus-time")
    if args.io_bitrate is not None:
        argv += ["--io-bitrate", str(args.io_bitrate)]
    if getattr(args, "firmware", "python") != "python":
        argv += ["--firmware", str(args.firmware)]
    return argv


def child_argv(
    role: str, bus_args: Sequence[str], *, node: int | None = None, extra: Sequence[str] = (), debug: bool = False
) -> list[str]:
    """Complete argv of one role: command (or test override) + role args + bus args."""
    own = ["--node", str(node)] if node is not None else []
    return role_command(role, node, debug=debug) + own + list(extra) + list(bus_args)


def bus_time_rates(args: argparse.Namespace) -> dict[str, int] | None:
    """``--bus-time``: the hub's bit rate per channel (``--io-bitrate``, the experiment's fieldbus bit
    rate), None without the option."""
    if not getattr(args, "bus_time", False):
        return None
    from host.experiment.console import experiment_config

    return {FIELDBUS: int(experiment_config(args).fieldbus_bitrate), IO_CHANNEL: int(args.io_bitrate or DEFAULT_BITRATE_BPS)}

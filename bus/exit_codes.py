"""The exit codes of every ``ilcrig`` command and role process — the one table of them.

This module owns :class:`ExitCode` and its module-level aliases.  Every process of the project
(the command line, the launchers, the roles, the hub, the sweep commands) exits with one of these;
docs/usage.md prints the same table (checked by tests/test_cli.py).

===  =====================  ==================================================================
0    ``OK``                 the command did what it was asked
1    ``ERROR``              an internal error (a bug): one line, the traceback in the log
2    ``USAGE``              bad input, one line ``ilcrig: error: …``, nothing was started
3    ``FAULT``              a fault during a run: torque removed, completed trials kept
4    ``CHILD_FAILED``       ``ilcrig run`` / ``ilcrig robot``: a role process could not be started
5    ``CLUSTER_LOST``       ``ilcrig sweep`` / ``ilcrig tune``: the Dask scheduler was lost or has no
                            workers; the finished points are kept and a resume runs the rest
129  ``HANGUP``             the terminal hung up (SIGHUP: its window closed, the ssh connection lost)
130  ``INTERRUPTED``        Ctrl-C (SIGINT)
143  ``TERMINATED``         SIGTERM
===  =====================  ==================================================================

May import: the standard library only.
"""

from __future__ import annotations

from enum import IntEnum

__all__ = [
    "ExitCode",
    "EXIT_OK",
    "EXIT_ERROR",
    "EXIT_USAGE",
    "EXIT_FAULT",
    "EXIT_CHILD_FAILED",
    "EXIT_CLUSTER_LOST",
    "EXIT_HANGUP",
    "EXIT_INTERRUPTED",
    "EXIT_TERMINATED",
    "exit_code_of_signal",
]


class ExitCode(IntEnum):
    """The exit codes (module docstring)."""

    OK = 0
    ERROR = 1
    USAGE = 2
    FAULT = 3
    CHILD_FAILED = 4
    CLUSTER_LOST = 5
    HANGUP = 129
    INTERRUPTED = 130
    TERMINATED = 143


#: the command did what it was asked
EXIT_OK: int = ExitCode.OK
#: an internal error (a bug): one line on the terminal, the traceback in the log
EXIT_ERROR: int = ExitCode.ERROR
#: bad input (one line ``ilcrig: error: …``), nothing was started
EXIT_USAGE: int = ExitCode.USAGE
#: a fault during a run — a drive, the plant, the hub or the host dying or stalling, io frames lost,
#: damaged, duplicated or late, an EMCY, a full disk: one line ``ilcrig: fault: …``, torque removed,
#: the completed trials kept in summary.json (``completed: false`` and a ``faults`` entry)
EXIT_FAULT: int = ExitCode.FAULT
#: ``ilcrig run`` / ``ilcrig robot``: a role process could not be started
EXIT_CHILD_FAILED: int = ExitCode.CHILD_FAILED
#: ``ilcrig sweep`` / ``ilcrig tune``: the Dask scheduler was lost or has no workers
EXIT_CLUSTER_LOST: int = ExitCode.CLUSTER_LOST
#: the terminal hung up (SIGHUP), unless it is ignored (``nohup``)
EXIT_HANGUP: int = ExitCode.HANGUP
#: interrupted by Ctrl-C (SIGINT)
EXIT_INTERRUPTED: int = ExitCode.INTERRUPTED
#: terminated by SIGTERM
EXIT_TERMINATED: int = ExitCode.TERMINATED


def exit_code_of_signal(signum: int) -> int:
    """The exit code of a run ended by signal ``signum``: 130 for SIGINT, 143 for SIGTERM, else
    128 + its number (the shell's convention)."""
    return 128 + int(signum)

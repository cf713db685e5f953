"""Starting a child process of the rig: the one spawn function and its one lifetime policy.

This module owns :func:`spawn_process`, which every process of the project that starts another
uses (the roles of ``ilcrig run`` / ``ilcrig robot``, the bus hub, the idle-poll loops, the run
folder's janitor, the ``ilcrig run`` of :class:`ilcrig.RigRun`).  The policy:

* **its own session** (``start_new_session``): the child leads a process group of its own, so the
  whole group can be signalled (:func:`killpg`) and a terminal's Ctrl-C or hang-up reaches only
  the process that started it;
* **a death signal** (``PR_SET_PDEATHSIG``, :data:`DEFAULT_DEATH_SIGNAL` = SIGKILL unless told
  otherwise), armed in the forked child before ``exec`` — before the child runs a line of its own
  code, so there is no moment in which the parent could die unnoticed; if the parent died between
  ``fork`` and ``prctl``, the child sends itself the signal at once.  ``None`` for a child that
  must outlive its parent (the janitor) or that ends on its own when the parent does (the hub:
  stdin EOF).  Linux sends it when the *thread* that started the child ends: start long-lived
  children from a thread that lives as long as they should;
* **stdin closed** unless given, descriptors other than 0-2 closed, optionally ``SCHED_BATCH``
  from the first instruction (``batch``).

Reaping and the cleanup on every exit path stay with the caller (:func:`host.rig.processes.terminate`,
:meth:`bus.transports.hub.process.HubHandle.stop`, …); :func:`killpg` signals one child's group.

May import: the standard library only.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

logger = logging.getLogger(__name__)

__all__ = ["DEFAULT_DEATH_SIGNAL", "killpg", "spawn_process"]

#: the signal a child gets when the thread that started it ends (``PR_SET_PDEATHSIG``)
DEFAULT_DEATH_SIGNAL: signal.Signals = signal.SIGKILL
_PR_SET_PDEATHSIG = 1


def _preexec(death_signal: int | None, batch: bool) -> Callable[[], None] | None:
    """``preexec_fn`` arming ``death_signal`` (and, with ``batch``, ``SCHED_BATCH``); None when
    there is nothing to do. The libc function is looked up here, in the parent: the child only calls it."""
    batch_policy = getattr(os, "SCHED_BATCH", None) if batch else None
    prctl: Any = None
    if death_signal is not None and sys.platform.startswith("linux"):
        try:
            prctl = ctypes.CDLL(None, use_errno=True).prctl
        except (OSError, AttributeError):  # pragma: no cover - glibc/musl always have prctl
            logger.warning("prctl unavailable: children will not die with a SIGKILLed parent")
        else:
            prctl.restype = ctypes.c_int
            prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    if prctl is None and batch_policy is None:
        return None
    parent = os.getpid()

    def preexec() -> None:
        if batch_policy is not None:
            os.sched_setscheduler(0, batch_policy, os.sched_param(0))
        if prctl is not None and death_signal is not None:
            prctl(_PR_SET_PDEATHSIG, int(death_signal), 0, 0, 0)
            if os.getppid() != parent:  # the parent died before prctl took effect
                os.kill(os.getpid(), int(death_signal))

    return preexec


def spawn_process(
    argv: Sequence[str],
    *,
    stdin: Any = subprocess.DEVNULL,
    stdout: Any = None,
    stderr: Any = None,
    death_signal: int | None = DEFAULT_DEATH_SIGNAL,
    batch: bool = False,
    env: Mapping[str, str] | None = None,
    text: bool = False,
) -> subprocess.Popen[Any]:
    """Start ``argv`` under the lifetime policy of the module docstring.

    :param stdin: / :param stdout: / :param stderr: as for :class:`subprocess.Popen`
        (stdin default: closed, ``/dev/null``)
    :param death_signal: signal to the child when its parent's thread ends (None: none)
    :param batch: start it in ``SCHED_BATCH`` (its threads inherit it)
    :param env: its environment (None: this process's)
    :param text: text streams for the pipes
    :raises OSError: it could not be started
    """
    proc: subprocess.Popen[Any] = subprocess.Popen(
        list(argv),
        stdin=stdin,
        stdout=stdout,
        stderr=stderr,
        start_new_session=True,
        preexec_fn=_preexec(death_signal, batch),
        close_fds=True,
        env=None if env is None else dict(env),
        text=text,
    )
    return proc


def killpg(pgid: int, signum: int) -> None:
    """Signal a child's process group (its own session); the child alone if that fails."""
    try:
        os.killpg(pgid, signum)
    except ProcessLookupError:
        pass
    except PermissionError:  # pragma: no cover - setsid failed: pgid is not ours
        with contextlib.suppress(ProcessLookupError):
            os.kill(pgid, signum)

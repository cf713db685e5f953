"""The hub as a child process: :func:`start_hub` and its :class:`HubHandle`.

This module owns starting a hub in a child process (``python -m bus.transports.hub.cli``),
waiting until it reports ready (:data:`READY_PREFIX` and its addresses on stdout), asking it for
its counters, and stopping and reaping it. The child exits when its stdin reaches EOF, so no hub
outlives the process that started it. The child is started with :func:`bus.processes.spawn_process`
(a session of its own; stdin EOF is its death signal).
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import subprocess
import sys
import tempfile
import time
import weakref
from collections.abc import Mapping, Sequence
from typing import Any, Self

from bus.processes import spawn_process
from bus.transports.hub.addresses import parse_address
from bus.transports.hub.bus_time import checked_bus_time
from bus.transports.hub.stats import HubChannelStats, query_hub_stats
from bus.transports.hub.wire import HubStartError

logger = logging.getLogger(__name__)

#: the first word of the line a hub started with ``--ready`` prints when it accepts clients
READY_PREFIX = "ILCRIG-HUB-READY"


def _reap(proc: subprocess.Popen[bytes], timeout_s: float) -> int:
    """Terminate (then kill) and wait for ``proc``; always reaps. Returns the exit code."""
    if proc.poll() is None:
        with contextlib.suppress(OSError):
            if proc.stdin is not None:
                proc.stdin.close()  # the hub exits on stdin EOF
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    for stream in (proc.stdin, proc.stdout):
        if stream is not None:
            with contextlib.suppress(OSError):
                stream.close()
    return int(proc.returncode)


class HubHandle:
    """A hub running in a child process (from :func:`start_hub`). Use as a context manager.

    :ivar addresses: the resolved listen addresses (TCP port 0 replaced by the real port)
    """

    def __init__(self, proc: subprocess.Popen[bytes], addresses: list[str], tmpdir: str | None) -> None:
        self.process = proc
        self.addresses = addresses
        self._tmpdir = tmpdir
        self._finalizer = weakref.finalize(self, HubHandle._cleanup, proc, tmpdir)

    @staticmethod
    def _cleanup(proc: subprocess.Popen[bytes], tmpdir: str | None) -> None:
        _reap(proc, 2.0)
        if tmpdir is not None:
            with contextlib.suppress(OSError):
                for name in os.listdir(tmpdir):
                    os.unlink(os.path.join(tmpdir, name))
                os.rmdir(tmpdir)

    @property
    def pid(self) -> int:
        return self.process.pid

    @property
    def address(self) -> str:
        """The first listen address, e.g. ``unix:/tmp/ilcrig-hub-x/hub.sock``."""
        return self.addresses[0]

    def channel(self, bus_name: str, address_index: int = 0) -> str:
        """The python-can channel string of logical bus ``bus_name`` on this hub."""
        return f"{self.addresses[address_index]}#{bus_name}"

    @property
    def alive(self) -> bool:
        return self.process.poll() is None

    def stats(self, reset: bool = False) -> dict[str, HubChannelStats]:
        """Per-bus counters of this hub (see :func:`query_hub_stats`)."""
        return query_hub_stats(self.address, reset=reset)

    def stop(self) -> int:
        """Stop the hub and reap the child process (idempotent). Returns its exit code."""
        self._finalizer()
        return int(self.process.returncode)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def start_hub(
    listen: str | Sequence[str] | None = None,
    *,
    timeout_s: float = 10.0,
    log_level: str = "WARNING",
    inject: str | None = None,
    stderr: Any = None,
    bus_time: Mapping[str, int] | None = None,
) -> HubHandle:
    """Start a hub in a child process and wait until it accepts clients.

    :param listen: address(es); default: ``hub.sock`` in a fresh private temp directory
        (removed again by :meth:`HubHandle.stop`)
    :param timeout_s: how long to wait for readiness, s
    :raises NonLoopbackAddressError: checked here already, before any process starts
    :raises HubStartError: the child exited or did not report ready in time (it is reaped)
    :param inject: frame faults for the hub (``--inject``, JSON of
        :meth:`bus.transports.fault_inject.FrameFaultInjector.from_json`)
    :param stderr: where the hub's stderr goes (default: inherited)
    :param bus_time: logical bus → bit rate, bit/s: deliver these buses in bus time (``--bus-time``)

    The child exits when :meth:`HubHandle.stop` closes its stdin, and also when this
    process dies (its stdin reaches EOF), so no hub outlives its parent.
    """
    tmpdir = None
    if listen is None:
        tmpdir = tempfile.mkdtemp(prefix="ilcrig-hub-")
        listen_list = [f"unix:{os.path.join(tmpdir, 'hub.sock')}"]
    else:
        listen_list = [listen] if isinstance(listen, str) else list(listen)
    for text in listen_list:
        parse_address(text)  # fail fast on a bad or non-loopback address
    # -P: the working folder is not on the hub's import path (a bus.py there must not shadow the package)
    cmd = [sys.executable, "-P", "-m", "host.cli", "hub", "--ready", "--exit-on-stdin-eof", "--log-level", log_level]
    for text in listen_list:
        cmd += ["--listen", text]
    if inject:
        cmd += ["--inject", inject]
    for name, rate in checked_bus_time(bus_time).items():
        cmd += ["--bus-time", f"{name}={rate}"]
    if tmpdir is not None:
        cmd += ["--remove-dir", tmpdir]  # the hub removes it when it exits, even if this process was killed
    # its own session (a terminal's Ctrl-C is its parent's); its death signal is stdin EOF, not
    # PR_SET_PDEATHSIG: it removes its socket folder on the way out
    proc = spawn_process(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=stderr, death_signal=None)
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    line = b""
    try:
        while not line.endswith(b"\n"):
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([proc.stdout], [], [], left)[0]:
                raise HubStartError(f"hub did not become ready within {timeout_s} s")
            chunk = os.read(proc.stdout.fileno(), 4096)
            if not chunk:
                raise HubStartError(f"hub exited during start-up (exit code {proc.wait()})")
            line += chunk
    except BaseException:
        HubHandle._cleanup(proc, tmpdir)
        raise
    parts = line.decode().split()
    if not parts or parts[0] != READY_PREFIX:
        HubHandle._cleanup(proc, tmpdir)
        raise HubStartError(f"unexpected hub start-up output {line!r}")
    handle = HubHandle(proc, parts[1:], tmpdir)
    logger.info("hub pid %d ready on %s", proc.pid, " ".join(parts[1:]))
    return handle

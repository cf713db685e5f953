"""python-can's own interface tests and tools, run against the ``ilcrig_hub`` interface.

python-can's tests are not copied into this repository, and this file never fetches them: the
explicit step ``scripts/fetch-python-can-tests`` (``.ci/run`` runs it) downloads the source
distribution of the *installed* python-can version with pip and extracts its ``test/`` folder to
``~/.cache/ilcrig/python-can-tests/<version>/pycan_upstream_tests`` (or
``$ILCRIG_PYCAN_TESTS_CACHE/<version>/…``). This file imports it from there as the package
``pycan_upstream_tests`` (not ``test``, which is the standard library's); when it is not there, those
tests are skipped, saying so. The tool tests at the end of this file (can.bridge, can.player) do not
need it.

What runs, and how it is pointed at the hub (one hub per module, a fresh logical bus per test):

* ``back2back_test``: ``Back2BackTestCase`` and ``TestThreadSafeBus`` subclassed with
  ``INTERFACE_1 = INTERFACE_2 = "ilcrig_hub"`` and ``CHANNEL_1 = CHANNEL_2`` = the test's
  logical bus (both buses on one hub bus, as python-can's own virtual run does).
* ``notifier_test``, ``listener_test.ListenerTest``, ``test_message_filtering``,
  ``simplecyclic_test``, ``zero_dlc_test``, ``contextmanager_test``: written for python-can's
  ``virtual`` interface; they run unchanged with the interface name ``virtual`` served by
  the hub (:class:`_VirtualOnHub`: virtual channel ``X`` → logical bus ``<test>-X``).

Not collected: ``listener_test.ListenerImportTest`` and ``listener_test.test_deprecated_loop_arg``
(they open no bus, so they say nothing about an interface). Tests that do not apply to the
hub are skipped with the reason written next to them below; python-can's own skips
(``IS_CI`` timing tests, its "TODO" direction tests) keep python-can's reason.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import itertools
import logging
import os
import select
import signal
import subprocess
import sys
import time
import types
import unittest
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, ClassVar

import can
import pytest

from bus.transports.hub.client import HubBus
from bus.transports.hub.process import HubHandle, start_hub

pytestmark = pytest.mark.multiprocess

PYCAN_VERSION = importlib.metadata.version("python-can")
UPSTREAM_PACKAGE = "pycan_upstream_tests"
UPSTREAM_MODULES = (
    "back2back_test",
    "notifier_test",
    "listener_test",
    "test_message_filtering",
    "simplecyclic_test",
    "zero_dlc_test",
    "contextmanager_test",
)
CACHE_ENV = "ILCRIG_PYCAN_TESTS_CACHE"


def _cache_dir() -> Path:
    root = os.environ.get(CACHE_ENV) or os.path.join(Path.home(), ".cache", "ilcrig", "python-can-tests")
    return Path(root) / PYCAN_VERSION


def _upstream_tests() -> Path:
    """The ``test/`` folder of python-can's sdist, as ``scripts/fetch-python-can-tests`` left it.

    :raises FileNotFoundError: it is not there (the step did not run, or could not download it)
    """
    pkg = _cache_dir() / UPSTREAM_PACKAGE
    if not ((pkg / "__init__.py").is_file() and (pkg / "back2back_test.py").is_file()):
        raise FileNotFoundError(
            f"python-can {PYCAN_VERSION}'s test suites are not in {pkg}: "
            "run scripts/fetch-python-can-tests (it needs the network once)"
        )
    return pkg


def _import_upstream() -> dict[str, types.ModuleType]:
    """python-can's test modules, imported as ``pycan_upstream_tests.<name>``.

    :raises FileNotFoundError: they were not fetched
    """
    pkg = _upstream_tests()
    if UPSTREAM_PACKAGE not in sys.modules:
        spec = importlib.util.spec_from_file_location(
            UPSTREAM_PACKAGE, pkg / "__init__.py", submodule_search_locations=[str(pkg)]
        )
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[UPSTREAM_PACKAGE] = module
        spec.loader.exec_module(module)
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    try:  # listener_test calls logging.basicConfig(level=DEBUG) at import: keep ours
        return {name: importlib.import_module(f"{UPSTREAM_PACKAGE}.{name}") for name in UPSTREAM_MODULES}
    finally:
        root.setLevel(level)
        root.handlers[:] = handlers


try:
    UP: dict[str, types.ModuleType] | None = _import_upstream()
    UPSTREAM_SKIP = ""
except FileNotFoundError as err:  # not fetched: skip those tests, saying why
    UP = None
    UPSTREAM_SKIP = str(err)


# ---------------------------------------------------------------------------------------
# the hub under test
# ---------------------------------------------------------------------------------------


class _VirtualOnHub(HubBus):
    """python-can's interface name ``virtual``, served by the hub: virtual channel ``X`` is
    the logical bus ``<test prefix>-X`` of :attr:`address` (set per test by ``_on_hub``)."""

    address: ClassVar[str] = ""
    prefix: ClassVar[str] = "t"

    def __init__(self, channel: Any = None, **kwargs: Any) -> None:
        for virtual_only in ("rx_queue_size", "preserve_timestamps", "protocol"):
            kwargs.pop(virtual_only, None)
        name = "channel-0" if channel is None else str(channel)
        super().__init__(f"{self.address}#{self.prefix}-{name}", **kwargs)


@pytest.fixture(scope="module")
def hub() -> Iterator[HubHandle]:
    with start_hub() as h:
        yield h


_TEST_NUMBER = itertools.count()


@pytest.fixture(autouse=True)
def _on_hub(request: pytest.FixtureRequest, hub: HubHandle, monkeypatch: pytest.MonkeyPatch) -> None:
    """A fresh logical bus per test: back2back channels, and ``virtual`` → the hub."""
    prefix = f"t{next(_TEST_NUMBER)}"
    monkeypatch.setattr(_VirtualOnHub, "address", hub.address)
    monkeypatch.setattr(_VirtualOnHub, "prefix", prefix)
    original = can.interface._get_class_for_interface

    def get_class(interface: str) -> type[can.BusABC]:
        return _VirtualOnHub if interface == "virtual" else original(interface)

    monkeypatch.setattr(can.interface, "_get_class_for_interface", get_class)
    instance = request.instance
    if UP is not None and isinstance(instance, UP["back2back_test"].Back2BackTestCase):
        instance.CHANNEL_1 = instance.CHANNEL_2 = hub.channel(prefix)  # type: ignore[attr-defined]


def _unskipped(test: Callable[..., None]) -> Callable[..., None]:
    """The test function under python-can's ``@unittest.skip`` (it keeps it as __wrapped__)."""
    return getattr(test, "__wrapped__", test)


_IS_RX_OWN = (
    "expects is_rx=True on a bus's own echoed frames; the hub marks them is_rx=False "
    "as SocketCAN does (python-can skips it too: 'TODO … should be done uniformly'); "
    "tests/test_hub.py::test_logical_buses_are_separate_and_echo_on_request covers the echo"
)
_VIRTUAL_QUEUE = "reads VirtualBus.queue, the virtual interface's internal receive queue (the hub has none)"


# ---------------------------------------------------------------------------------------
# python-can's test classes on the hub
# ---------------------------------------------------------------------------------------

if UP is not None:
    _b2b = UP["back2back_test"]

    class TestHubBack2Back(_b2b.Back2BackTestCase):  # type: ignore[name-defined,misc]
        """python-can's back-to-back tests, both buses on one logical hub bus."""

        INTERFACE_1 = INTERFACE_2 = "ilcrig_hub"

        # python-can skips it for want of a uniform rule; for the hub the rule is clear
        # (a received frame is_rx=True), so it runs here
        test_message_is_rx = _unskipped(_b2b.Back2BackTestCase.test_message_is_rx)

        @unittest.skip(_IS_RX_OWN)
        def test_message_is_rx_receive_own_messages(self) -> None: ...

    class TestHubThreadSafeBack2Back(_b2b.TestThreadSafeBus):  # type: ignore[name-defined,misc]
        """The same through can.ThreadSafeBus, plus 1000 frames from 100 threads, filtered or not."""

        INTERFACE_1 = INTERFACE_2 = "ilcrig_hub"
        test_message_is_rx = _unskipped(_b2b.Back2BackTestCase.test_message_is_rx)

        @unittest.skip(_IS_RX_OWN)
        def test_message_is_rx_receive_own_messages(self) -> None: ...

    class TestHubNotifier(UP["notifier_test"].NotifierTest):  # type: ignore[name-defined,misc]
        @unittest.skip(
            "asserts the virtual interface's integer channel ids (recv_msg.channel == 0 / 1); "
            "a hub bus's msg.channel is its channel string, see "
            "tests/test_hub.py::test_notifier_over_two_hub_buses_keeps_each_channel"
        )
        def test_multiple_bus(self) -> None: ...

    class TestHubAsyncNotifier(UP["notifier_test"].AsyncNotifierTest):  # type: ignore[name-defined,misc]
        pass

    class TestHubListener(UP["listener_test"].ListenerTest):  # type: ignore[name-defined,misc]
        pass

    class TestHubMessageFiltering(UP["test_message_filtering"].TestMessageFiltering):  # type: ignore[name-defined,misc]
        pass

    class TestHubCyclicSend(UP["simplecyclic_test"].SimpleCyclicSendTaskTest):  # type: ignore[name-defined,misc]
        @unittest.skip(_VIRTUAL_QUEUE)
        def test_cycle_time(self) -> None: ...

        @unittest.skip(_VIRTUAL_QUEUE)
        def test_restart_perodic_tasks(self) -> None: ...

    class TestHubZeroDlc(UP["zero_dlc_test"].ZeroDLCTest):  # type: ignore[name-defined,misc]
        pass

    class TestHubContextManager(UP["contextmanager_test"].ContextManagerTest):  # type: ignore[name-defined,misc]
        pass

else:

    @pytest.mark.skip(reason=UPSTREAM_SKIP)
    def test_python_can_interface_suites() -> None:
        """python-can's suites are not fetched here (the reason in the skip)."""


# ---------------------------------------------------------------------------------------
# python-can's tools over the hub
# ---------------------------------------------------------------------------------------


#: longest the bridge may take to start, or to stop after Ctrl-C, s (a bound on a hang only)
TOOL_WAIT_S = 120.0
#: ``python -m can.bridge ARGS``, which prints one more line once it is in the loop that a Ctrl-C
#: ends (python-can's own "Started" line comes just before that loop: a Ctrl-C between the two ends
#: it with a KeyboardInterrupt traceback). Unbuffered; SIGINT reaches it as KeyboardInterrupt however
#: pytest was started (tests/conftest.py).
_BRIDGE = """
import sys, time, types
import can.bridge as bridge

def sleep(seconds):
    bridge.time = time
    print("bridge looping", flush=True)
    time.sleep(seconds)

bridge.time = types.SimpleNamespace(sleep=sleep)
bridge.main()
"""


def _start_bridge(*args: str) -> subprocess.Popen[str]:
    cmd = [sys.executable, "-c", _BRIDGE, *args]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def _wait_for_line(proc: subprocess.Popen[str], line: str, timeout_s: float) -> bool:
    """Whether ``proc`` printed ``line`` on stdout before it exited (or ``timeout_s`` s passed)."""
    assert proc.stdout is not None
    fd = proc.stdout.fileno()  # read unbuffered: select() does not see what a buffer holds
    deadline = time.monotonic() + timeout_s
    seen = b""
    while line.encode() not in seen.splitlines():
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([fd], [], [], left)[0]:
            return False
        chunk = os.read(fd, 4096)
        if not chunk:
            return False
        seen += chunk
    return True


def _stop(proc: subprocess.Popen[str]) -> tuple[int, str]:
    """Ctrl-C (SIGINT), then wait for the exit; (exit code, stderr)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=TOOL_WAIT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
    return proc.returncode, err


FRAMES = [
    can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02"),
    can.Message(arbitration_id=0x1ABCDEF, is_extended_id=True, data=b""),
    can.Message(arbitration_id=0x321, is_extended_id=False, is_remote_frame=True, dlc=3),
    can.Message(arbitration_id=0x7FF, is_extended_id=False, is_fd=True, bitrate_switch=True, data=bytes(range(64))),
    can.Message(arbitration_id=0x18FF00AA, is_extended_id=True, is_fd=True, error_state_indicator=True, data=bytes(12)),
]


def _same(a: can.Message, b: can.Message) -> bool:
    return a.equals(b, timestamp_delta=None, check_channel=False, check_direction=False)


def test_can_bridge_joins_two_hub_buses(hub: HubHandle) -> None:
    """``python -m can.bridge`` between two logical buses of the hub, both directions; it stops on
    Ctrl-C with exit code 0."""
    with HubBus(hub.channel("bra")) as a, HubBus(hub.channel("brb")) as b:
        proc = _start_bridge(
            "--bus1-interface",
            "ilcrig_hub",
            "--bus1-channel",
            hub.channel("bra"),
            "--bus2-interface",
            "ilcrig_hub",
            "--bus2-channel",
            hub.channel("brb"),
        )
        try:
            # both buses open, both directions forwarded, waiting for Ctrl-C
            assert _wait_for_line(proc, "bridge looping", TOOL_WAIT_S), "the bridge did not start"
            for m in FRAMES:
                a.send(m)
                got = b.recv(5.0)
                assert got is not None and _same(got, m) and got.channel == hub.channel("brb")
                b.send(m)
                got = a.recv(5.0)
                assert got is not None and _same(got, m) and got.channel == hub.channel("bra")
        finally:
            code, err = _stop(proc)
    assert code == 0, err


def test_can_player_replays_a_log_onto_the_hub(hub: HubHandle, tmp_path: Path) -> None:
    """``python -m can.player`` sends a candump log's frames (FD, BRS, ESI, remote, empty) to a hub bus."""
    log = tmp_path / "in.log"
    with can.CanutilsLogWriter(log, channel="io") as writer:
        for i, m in enumerate(FRAMES):
            m.timestamp = 1000.0 + i * 0.001
            writer.on_message_received(m)
    expected = list(can.LogReader(log))  # what the candump format keeps (a remote frame's DLC: not)
    with HubBus(hub.channel("play")) as rx:
        res = subprocess.run(
            [sys.executable, "-m", "can.player", "-i", "ilcrig_hub", "-c", hub.channel("play"), "--ignore-timestamps", str(log)],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert res.returncode == 0, res.stderr
        got = [rx.recv(5.0) for _ in expected]
    assert all(g is not None and _same(g, e) for g, e in zip(got, expected, strict=True)), got

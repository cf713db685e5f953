"""python-can's own interface tests and tools, run against the ``ilcrig_hub`` interface.

python-can's tests are not copied into this repository. At collection time the source
distribution of the *installed* python-can version is fetched with pip (``pip download
--no-binary :all: --no-deps python-can==<version>``) into
``~/.cache/ilcrig/python-can-tests/<version>/`` (or ``$ILCRIG_PYCAN_TESTS_CACHE/<version>/``),
its ``test/`` folder is extracted there once, and imported as the package
``pycan_upstream_tests`` (not ``test``, which is the standard library's). When it cannot be
fetched (offline, no cache) those tests are skipped with pip's reason; the tool tests at
the end of this file (can.bridge, can.player) do not need it.

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

import contextlib
import importlib
import importlib.metadata
import importlib.util
import itertools
import logging
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
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


def _fetch_upstream_tests() -> Path:
    """The extracted ``test/`` folder of python-can's sdist (downloaded once per version).

    :raises RuntimeError: pip could not download it (its output in the message)
    """
    pkg = _cache_dir() / UPSTREAM_PACKAGE
    if (pkg / "__init__.py").is_file() and (pkg / "back2back_test.py").is_file():
        return pkg
    pkg.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=pkg.parent) as tmp:
        cmd = [
            sys.executable,
            "-m",
            "pip",
            "download",
            "--no-binary",
            ":all:",
            "--no-deps",
            "--disable-pip-version-check",
            "--timeout",
            "20",
            "--retries",
            "1",
            "-d",
            tmp,
            f"python-can=={PYCAN_VERSION}",
        ]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
        sdists = sorted(Path(tmp).glob("python[-_]can-*.tar.gz"))
        if res.returncode != 0 or not sdists:
            tail = " | ".join((res.stderr or res.stdout).strip().splitlines()[-3:])
            raise RuntimeError(f"cannot download the python-can {PYCAN_VERSION} sdist ({shlex.join(cmd)}): {tail}")
        staged = Path(tmp) / UPSTREAM_PACKAGE
        with tarfile.open(sdists[0]) as tar:
            members = [m for m in tar.getmembers() if m.name.split("/")[1:2] == ["test"] and (m.isfile() or m.isdir())]
            tar.extractall(Path(tmp) / "x", members=members, filter="data")
        shutil.move(str(next((Path(tmp) / "x").iterdir()) / "test"), staged)
        with contextlib.suppress(OSError):  # another run may have finished first: keep its copy
            staged.rename(pkg)
    return pkg


def _import_upstream() -> dict[str, types.ModuleType]:
    """python-can's test modules, imported as ``pycan_upstream_tests.<name>``."""
    pkg = _fetch_upstream_tests()
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
except Exception as err:  # offline and not cached: skip those tests, saying why
    UP = None
    UPSTREAM_SKIP = f"python-can's test suite not available: {err}"


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
        """Placeholder: python-can's suites could not be fetched (reason in the skip)."""


# ---------------------------------------------------------------------------------------
# python-can's tools over the hub
# ---------------------------------------------------------------------------------------


def _wait_until(condition: Callable[[], bool], timeout_s: float) -> bool:
    """Poll ``condition`` (a state only the hub knows: who joined) until true."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def _members(hub: HubHandle, bus: str) -> int:
    st = hub.stats().get(bus)
    return st.clients if st is not None else 0


def _stop(proc: subprocess.Popen[str]) -> tuple[int, str]:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=15)
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
    """``python -m can.bridge`` between two logical buses of the hub, both directions."""
    with HubBus(hub.channel("bra")) as a, HubBus(hub.channel("brb")) as b:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "can.bridge",
                "--bus1-interface",
                "ilcrig_hub",
                "--bus1-channel",
                hub.channel("bra"),
                "--bus2-interface",
                "ilcrig_hub",
                "--bus2-channel",
                hub.channel("brb"),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            assert _wait_until(lambda: _members(hub, "bra") == 2 and _members(hub, "brb") == 2, 30), "bridge did not join"
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

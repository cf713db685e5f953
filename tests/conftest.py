"""pytest hooks shared by the test suite.

This file owns the test tiers (:func:`pytest_collection_modifyitems`): the README's ``pytest`` runs
the fast tier; ``pytest -m full`` runs the full tier, every test the fast tier leaves out — the ones
marked ``slow``, ``multiprocess``, ``faultmatrix``, ``netns``, ``vcan`` or ``pil`` get the ``full`` marker here,
except those marked ``fast`` (one rig per transport, kept in the fast tier). ``pytest -m ""`` runs
both. docs/development.md describes them.

It also owns two rules. Under ``CI=true`` a *skipped* ``vcan`` test is a failure when
the vcan suite was asked for (``-m vcan``, as ``scripts/vcan-tests`` runs it, or
``ILCRIG_REQUIRE_VCAN=1``): in CI the suite must really run on SocketCAN, not quietly skip.
The ordinary ``pytest`` run (no ``-m vcan``) keeps skipping vcan tests on kernels without vcan.
A failing test that wrote a run folder under its ``tmp_path`` shows the tails of the run's role
logs (``logs/*.log``, their INFO records and above) in its report (:func:`run_logs_of`): a flake in
CI leaves its evidence in CI's output, where the run folder does not outlive the machine.
And the processes the tests start take SIGINT (Ctrl-C) as Python's KeyboardInterrupt however the
test runner was started (:func:`pytest_configure`). It also holds the ``hub_data_plane`` fixture
and the ``sleeper`` fixture (a process to schedule).
"""

from __future__ import annotations

import compileall
import logging
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

logger = logging.getLogger(__name__)

_TRUE = ("1", "true", "yes")


def pytest_configure(config: pytest.Config) -> None:
    """A runner started with SIGINT and SIGQUIT ignored (pytest in the background of a
    non-interactive shell, ``( pytest & )``) would pass that on to every process the tests start,
    since an ignored signal stays ignored across exec: a tool the tests stop with Ctrl-C
    (``can.bridge``, ``can.logger``) would never stop, and a launcher the tests end with Ctrl-\\
    would outlive it. Python's own handler for SIGINT instead (a handled signal is back to its
    default across exec, where Python installs its KeyboardInterrupt again), the default for SIGQUIT."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if signal.getsignal(signal.SIGQUIT) == signal.SIG_IGN:
        signal.signal(signal.SIGQUIT, signal.SIG_DFL)
    compile_project()


#: the checkout (the project's packages are its folders with an ``__init__.py``)
REPO = Path(__file__).resolve().parent.parent


def compile_project() -> None:
    """The project's bytecode written once, before the tests start processes: with
    ``PYTHONDONTWRITEBYTECODE`` set (as on the CI machines here) no process writes it, and every
    process a test starts (six or seven a rig) compiled ~130 modules from source again, ≈ 0.1 s of
    CPU each (docs/benchmarks.md "The test tiers"). ``compileall`` writes it anyway; a read-only
    checkout (the vcan VM's view of it) is left as it is."""
    for pkg in sorted(p for p in REPO.iterdir() if (p / "__init__.py").is_file()):
        compileall.compile_dir(pkg, quiet=2)


#: the markers of a test that belongs to the full tier (unless it is also marked ``fast``)
FULL_TIER_MARKERS = ("slow", "multiprocess", "faultmatrix", "netns", "vcan", "pil")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark every test of the full tier ``full`` (module docstring), before ``-m`` selects."""
    for item in items:
        if item.get_closest_marker("fast") is None and any(item.get_closest_marker(m) for m in FULL_TIER_MARKERS):
            item.add_marker(pytest.mark.full)


def _vcan_required(config: pytest.Config) -> bool:
    if os.environ.get("ILCRIG_REQUIRE_VCAN", "").strip().lower() in _TRUE:
        return True
    markexpr = (config.getoption("markexpr", "") or "").strip()
    return os.environ.get("CI", "").strip().lower() in _TRUE and markexpr == "vcan"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):  # type: ignore[no-untyped-def]
    outcome = yield
    report = outcome.get_result()
    if report.skipped and item.get_closest_marker("vcan") is not None and _vcan_required(item.config):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        report.outcome = "failed"
        report.longrepr = f"vcan test skipped where it must run (CI=true, -m vcan): {reason}"
    if report.failed and report.when == "call":
        tmp = getattr(item, "funcargs", {}).get("tmp_path")
        logs = run_logs_of(tmp) if isinstance(tmp, Path) else ""
        if logs:
            report.sections.append(("the run's role logs (tails, INFO and above)", logs))


#: how many lines of each role log a failing test's report shows, and of how many logs at most
RUN_LOG_TAIL_LINES = 40
RUN_LOGS_MAX = 40


def run_logs_of(root: Path) -> str:
    """The last :data:`RUN_LOG_TAIL_LINES` lines (DEBUG left out) of every ``logs/*.log`` of the
    run folders under ``root``, each under its path; '' when there are none."""
    parts = []
    for log in sorted(root.glob("**/logs/*.log"))[:RUN_LOGS_MAX]:
        try:
            text = log.read_text(errors="replace")
            lines = [ln for ln in text.splitlines() if " DEBUG " not in ln and not ln.startswith("DEBUG ")]
        except OSError:
            continue
        if lines:
            parts.append(f"== {log.relative_to(root)}\n" + "\n".join(lines[-RUN_LOG_TAIL_LINES:]))
    return "\n".join(parts)


@pytest.fixture(params=["c", "python"])
def hub_data_plane(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run a hub test once with each data plane of the hub: the C core (skipped where it is not
    built) and the pure-Python path. Hubs started by the test, in-process or as child processes,
    take it from the environment (bus.transports.hub.core.HUB_CORE_ENV), and so do the hub
    clients it opens (with ``python`` none answers frames in C: HubBus.answers_in_c)."""
    from bus.transports.hub.core import HUB_CORE_ENV, core_built

    if request.param == "c" and not core_built():
        pytest.skip("the hub's C core is not built here (no C compiler at install)")
    monkeypatch.setenv(HUB_CORE_ENV, request.param)
    return str(request.param)


@pytest.fixture
def sleeper() -> Iterator[subprocess.Popen[bytes]]:
    """A child process of two threads that sleep 60 s (something to schedule), killed after the test."""
    proc = subprocess.Popen(
        [sys.executable, "-c", "import threading, time; threading.Thread(target=time.sleep, args=(60,)).start(); time.sleep(60)"],
        stdin=subprocess.DEVNULL,
    )
    try:
        yield proc
    finally:
        proc.kill()
        proc.wait()


@pytest.fixture
def no_leaked_virtual_channels() -> Iterator[None]:
    """The test closes every python-can ``virtual`` bus it opened (a module uses it for all its tests)."""
    from can.interfaces import virtual

    yield
    assert not virtual.channels, f"virtual channels left open: {list(virtual.channels)}"

"""A record's writer (bus.process_identity): alive while it runs, gone after it ended — across pid
reuse, reboots and other machines — and what a reader makes of an unfinished summary."""

from __future__ import annotations

import subprocess
import sys

from bus.process_identity import identity_alive, process_identity
from host.experiment.outputs import end_reason_of


def test_this_process_is_alive_and_an_ended_one_is_gone() -> None:
    me = process_identity()
    assert me["start_ticks"] is not None and me["boot_id"]
    assert identity_alive(me) is True
    child = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"], stdin=subprocess.PIPE)
    try:
        ident = process_identity(child.pid)
        assert identity_alive(ident) is True
    finally:
        assert child.stdin is not None
        child.stdin.close()
        child.wait()
    assert identity_alive(ident) is False


def test_a_reused_pid_another_boot_and_another_host() -> None:
    me = process_identity()
    assert identity_alive(me | {"start_ticks": me["start_ticks"] + 1}) is False  # the pid, reused
    assert identity_alive(me | {"boot_id": "00000000-0000-0000-0000-000000000000"}) is False  # rebooted since
    assert identity_alive(me | {"host": me["host"] + "-elsewhere"}) is None  # cannot tell from here
    assert identity_alive(None) is None and identity_alive({"pid": "1"}) is None


def test_an_unfinished_summary_reads_as_running_until_its_writer_is_gone() -> None:
    me = process_identity()
    assert end_reason_of({"end_reason": None, "writer": me}) is None
    assert end_reason_of({"end_reason": None, "writer": me | {"start_ticks": me["start_ticks"] + 1}}) == "writer_lost"
    assert end_reason_of({"end_reason": "completed", "writer": me | {"start_ticks": 0}}) == "completed"
    assert end_reason_of({"end_reason": None}) is None  # an older summary without a writer: cannot tell

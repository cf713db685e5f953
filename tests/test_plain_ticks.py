"""A trial's plain io ticks run by the firmware's C core (firmware_model/plain_ticks.py,
``TrialTicker`` in firmware_model/_fwcore.c) do what the firmware's Python path does.

From outside: a real drive through a whole trial on a hub sends the same torque frames, records
the same trace and ends in the same state with the ticker as without it (``ILCRIG_PLAIN_TICKS=python``),
for the Python model's kernel and for the C core's, and the ticker ran every tick but the first
and the last; and, at random, two drives fed the same encoder frames (counts anywhere, ticks
skipped or repeated, a following-error window that trips, the service's deadline passing, the
answer loop returning at any frame, a homing offset up to saturation) — one through the ticker,
one through the Python path — answer every frame alike and hold the same state after each."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from hub_util import serving_in
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_drive_answer import NODE, _trial, playing_drive
from test_drive_client import reference

from bus import io_frames
from bus.transports.hub.core import HUB_CORE_ENV, core_built
from bus.units import rad_to_counts
from firmware_model.drive import Drive
from firmware_model.drive_node import DriveNode
from firmware_model.firmware_select import c_available
from firmware_model.plain_ticks import PLAIN_TICKS_ENV, PlainTicks, plain_ticks_for

pytestmark = pytest.mark.skipif(
    not (core_built() and c_available()), reason="the C cores are not built here (no C compiler at install)"
)

FIRMWARES = ["python", "c"]


# ------------------------------------------------------------------ a real drive through a trial


@pytest.mark.parametrize("firmware", FIRMWARES)
def test_a_trial_through_the_ticker_is_the_trial_of_the_python_path(
    firmware: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    n = 301
    monkeypatch.delenv(HUB_CORE_ENV, raising=False)
    runs = {}
    for plain in ("c", "python"):
        monkeypatch.setenv(PLAIN_TICKS_ENV, plain)
        (tmp_path / plain).mkdir()
        with serving_in(tmp_path / plain, "c") as server:
            runs[plain] = _trial(server, n, firmware=firmware)
    ticker, python = runs["c"], runs["python"]
    assert ticker.torques == python.torques and np.array_equal(ticker.trace, python.trace)
    assert [struct.unpack("<iHB", d)[0] for _, d in ticker.torques] == list(ticker.trace)
    assert ticker.answered == python.answered == n - 1
    # all but tick 0 (the start frame's wake-up is served first) and the last (it ends the trial)
    assert ticker.ran_in_c == n - 2 and python.ran_in_c == 0
    assert ticker.state == python.state


# ------------------------------------------------------------------ the ticker against the Python path, at random


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class _Twin:
    """A drive in a trial on virtual buses, its node's callback driven by hand as the answer loop
    drives it: the ticker (armed at each start of the loop) or the Python path alone."""

    def __init__(self, name: str, firmware: str, n_ticks: int, fe_window: int, offset: int, clock: _Clock, ticker: bool) -> None:
        drive, _ = playing_drive(n_ticks, firmware, 0.05, fe_window, offset)
        self.io = can.Bus(interface="virtual", channel=f"plain-io-{name}", receive_own_messages=False)
        self.fieldbus = can.Bus(interface="virtual", channel=f"plain-fb-{name}")
        self.wire = can.Bus(interface="virtual", channel=f"plain-io-{name}")  # the plant's end
        self.drive = drive
        self.node = DriveNode(drive, self.fieldbus, self.io, clock=clock)
        self.node.on_io(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_START, 0, n_ticks))
        self.node._serve_by_s = 1.0  # the service's deadline (a white-box test: its own time)
        self.plain: PlainTicks | None = None
        if ticker:
            node = self.node
            self.plain = PlainTicks(drive, node._answer_tick, clock, node, node._torque_id, node._torque_status)
        self.callback: Any = None

    def loop_starts(self) -> None:
        node = self.node
        if self.plain is not None and node.backlog.quiet:
            self.callback = self.plain.on_frame(node._next_full_tick, node._tick_origin, node.frames_out, node._serve_by_s)
        else:
            self.callback = node._answer_tick

    def loop_ends(self) -> None:
        if self.plain is not None:
            self.plain.disarm()
        self.callback = None

    def frame(self, data: bytes) -> tuple[Any, list[tuple[int, bytes]]]:
        """The loop hands over one encoder frame: the answers, and what went on the wire besides."""
        if self.callback is None:
            self.loop_starts()
        answers = self.callback(0, data)
        if answers is None:
            self.loop_ends()  # the loop returns when its callback handled a frame itself
        sent = []
        while (msg := self.wire.recv(0)) is not None:
            sent.append((msg.arbitration_id, bytes(msg.data)))
        return (None if answers is None else [(i, bytes(d)) for i, d in answers]), sent

    def state(self) -> dict[str, Any]:
        drive, node = self.drive, self.node
        return {
            "st": drive.motion.mode.st.tolist(),
            "rec": drive.trial.rec.tobytes(),
            "time_us": drive.time_us,
            "trial": (int(drive.trial.state), drive.trial.next_tick),
            "statusword": int(drive.statusword),
            "emcy": list(drive.power._emcy),
            "node": (node.frames_out, node._next_full_tick),
        }

    def close(self) -> None:
        for bus in (self.io, self.fieldbus, self.wire):
            bus.shutdown()


@pytest.fixture
def twins() -> Iterator[list[_Twin]]:
    made: list[_Twin] = []
    yield made
    for twin in made:
        twin.close()


_TICK = st.tuples(  # an encoder frame: its wire tick against the next one in order, its count against the reference
    st.just("tick"),
    st.sampled_from([0] * 60 + [-2, -1, 1, 2]),
    st.one_of(*[st.integers(-2_000, 2_000)] * 15, st.integers(-(2**31), 2**31 - 1)),
)
#: mostly frames in order, the loop returning now and then (the ticker armed anew), time passing (the
#: service's deadline is at 1 s)
_STEP = st.one_of(*[_TICK] * 8, *[st.just(("loop returns",))] * 3, st.tuples(st.just("clock"), st.floats(0.0, 0.3)))


@pytest.mark.parametrize("firmware", FIRMWARES)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    n_ticks=st.integers(3, 60),
    fe_window=st.sampled_from([-1, 2_000, 50_000]),
    offset=st.sampled_from([0, 0, 12_345, -(2**31) + 5, 2**31 - 5]),
    steps=st.lists(_STEP, min_size=20, max_size=120),
)
def test_the_ticker_answers_and_changes_what_the_python_path_does(
    firmware: str, n_ticks: int, fe_window: int, offset: int, steps: list[tuple[Any, ...]], twins: list[_Twin]
) -> None:
    clock = _Clock()
    k = len(twins)
    ticker = _Twin(f"t{k}", firmware, n_ticks, fe_window, offset, clock, ticker=True)
    python = _Twin(f"p{k}", firmware, n_ticks, fe_window, offset, clock, ticker=False)
    twins += [ticker, python]
    q, _, _ = reference(n_ticks, amp=0.05)
    wire = 0
    for step in steps:
        if step[0] == "tick":
            _, skew, jitter = step
            tick = max(wire + skew, 0)
            count = rad_to_counts(float(q[min(tick, n_ticks - 1)])) + jitter
            data = struct.pack("<iH", max(min(count, 2**31 - 1), -(2**31)), tick & 0xFFFF)
            got, want = ticker.frame(data), python.frame(data)
            assert got == want, f"tick {tick}: {got} != {want}"
            wire = tick + 1
        elif step[0] == "loop returns":
            for twin in (ticker, python):
                twin.loop_ends()
        else:
            clock.now += step[1]
        assert ticker.state() == python.state()
    if ticker.plain is not None and fe_window < 0:
        assert ticker.plain.ticks <= n_ticks


def test_only_the_firmware_model_has_a_ticker_and_the_switch_turns_it_off(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    drive = Drive(NODE)

    def fallback(index: int, data: bytes) -> None:
        return None

    assert plain_ticks_for(object(), fallback, _Clock(), object(), 0x181, lambda: 0) is None
    assert plain_ticks_for(drive, fallback, _Clock(), object(), 0x181, lambda: 0) is not None
    monkeypatch.setenv(PLAIN_TICKS_ENV, "python")
    assert plain_ticks_for(drive, fallback, _Clock(), object(), 0x181, lambda: 0) is None


def test_the_ticker_checks_what_it_is_armed_with_and_never_writes_outside_its_arrays() -> None:
    from firmware_model import _fwcore, control_law

    calls: list[tuple[int, bytes]] = []

    def fallback(index: int, data: bytes) -> list[tuple[int, bytes]]:
        calls.append((index, data))
        return []

    class Obj:
        pass

    ticker = _fwcore.TrialTicker(fallback, _Clock(), _fwcore.control_tick, Obj(), Obj(), Obj(), 0x181)
    st_, tables, rec = control_law.new_state(), control_law.new_tables(4), control_law.new_recorder(4)
    good = (st_, tables, rec, 0, 4, 0, 0, 0, 1000, 0, 0, 1.0, 1, 9)
    with pytest.raises(TypeError):
        ticker.arm(st_.astype(np.int32), *good[1:])
    with pytest.raises(ValueError):
        ticker.arm(st_, control_law.new_tables(4)[:2].copy(), *good[2:])
    with pytest.raises(ValueError):
        ticker.arm(*good[:12], 256, 9)  # a status outside a byte
    with pytest.raises(TypeError):
        ticker.arm(*good[:5])
    assert not ticker.armed
    assert ticker(0, struct.pack("<iH", 5, 0)) == [] and len(calls) == 1  # disarmed: the Python path's
    ticker.arm(*good)
    assert ticker.armed
    answer = ticker(0, struct.pack("<iH", 5, 0))
    assert answer is not None and answer[0][0] == 0x181 and ticker.ticks == 1 and len(calls) == 1
    ticker.arm(st_, tables, rec, 2, 99, 2, 0, 0, 1000, 0, 0, 1.0, 1, 9)  # 99 ticks, 4 columns
    before = rec.copy()
    for k in (2, 3):
        assert ticker(0, struct.pack("<iH", 5, k)) is not None
    assert ticker(0, struct.pack("<iH", 5, 4)) == [] and not ticker.armed  # column 4: the Python path's
    assert len(calls) == 2 and ticker.ticks == 3 and np.array_equal(rec[:, :2], before[:, :2])
    ticker.arm(*good)
    assert ticker(0, b"\x00" * 5) == [] and not ticker.armed  # not an encoder frame's data

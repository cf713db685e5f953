"""A drive's plain io ticks answered in C: the hub client's loop (``_hubcore.answer_frames``,
:meth:`bus.transports.hub.client.HubBus.answer_frames`) and the drive node that uses it
(:meth:`firmware_model.drive_node.DriveNode.step`).

From outside: records split anyhow over the reads are answered in order up to the first record that
is not a plain encoder frame, and every byte after it comes back; each way the loop can return
(deadline, the other descriptor, another frame, the callable's own handling, an exception, the hub
gone) leaves the client reading what a client that never answered in C would read; a real drive
through a whole trial on a hub sends the same torque frames, records the same trace and counts its
ticks answered in C, against the same drive with the C loop switched off (``ILCRIG_HUB_CORE=python``)."""

from __future__ import annotations

import contextlib
import math
import os
import signal
import socket
import struct
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

import can
import numpy as np
import pytest
from clock_util import wait_for
from hub_util import serving, serving_in
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule
from test_drive_client import DoubleIntegrator, reference

from bus import io_frames
from bus.bus_features import AnswerEnd, FrameAnswerer, frame_answerer
from bus.objects import Obj
from bus.transports.hub.client import HubBus
from bus.transports.hub.core import HUB_CORE_ENV, core_built, member_core
from bus.transports.hub.server import HubServer
from bus.transports.hub.wire import HEADER, KIND_FRAME
from firmware_model.drive import Drive
from firmware_model.drive_node import DriveNode
from host.nodes.drive_client import DriveClient

pytestmark = pytest.mark.skipif(not core_built(), reason="the hub's C core is not built here (no C compiler at install)")

ENC_ID, TORQUE_ID = 0x101, 0x181
NODE = 2


def _rec(can_id: int, data: bytes, flags: int = 0) -> bytes:
    return HEADER.pack(KIND_FRAME, flags, len(data), len(data), can_id, 0, data)


def _torque(data: bytes) -> bytes:
    count, wire = struct.unpack("<iH", data)
    return struct.pack("<iHB", -count, wire, 1)


def _answer(index: int, data: bytes) -> list[tuple[int, bytes]]:
    return [(TORQUE_ID, _torque(data))]


# ------------------------------------------------------------------ the C loop on a socket pair

_OTHER = st.one_of(
    st.tuples(st.just(0x102), st.just(6), st.just(0)),  # another joint's encoder frame
    st.tuples(st.just(ENC_ID), st.sampled_from([0, 5, 7, 8]), st.just(0)),  # the encoder id, another length
    st.tuples(st.just(ENC_ID), st.just(6), st.sampled_from([0x02, 0x04, 0x40])),  # remote, error, echo flags
    st.tuples(st.just(io_frames.CONTROL_COB_ID), st.just(7), st.just(0)),  # a control frame
)


@given(
    plain=st.integers(0, 40),
    other=_OTHER,
    tail=st.integers(0, 5),
    cuts=st.lists(st.integers(1, 60), min_size=1, max_size=30),
)
@settings(max_examples=60, deadline=None)
def test_records_split_anyhow_are_answered_in_order_and_the_rest_comes_back(
    plain: int, other: tuple[int, int, int], tail: int, cuts: list[int]
) -> None:
    """``plain`` encoder frames, then one record that is anything else, then ``tail`` more encoder
    frames, written in chunks of the drawn sizes (cut anywhere, inside records too) by another
    thread: the loop answers exactly the ``plain`` frames, in order, one torque record each, and
    returns at the other record with every byte from it on, read or still in the socket."""
    core = member_core()
    assert core is not None
    ids, length, flags = other
    plain_recs = [_rec(ENC_ID, struct.pack("<iH", 1000 + k, k)) for k in range(plain)]
    stream = b"".join(plain_recs) + _rec(ids, bytes(range(length)), flags)
    stream += b"".join(_rec(ENC_ID, struct.pack("<iH", 5000 + k, k)) for k in range(tail))
    chunks, off, i = [], 0, 0
    while off < len(stream):
        n = cuts[i % len(cuts)]
        chunks.append(stream[off : off + n])
        off, i = off + n, i + 1
    here, there = socket.socketpair()
    seen: list[bytes] = []

    def on_frame(index: int, data: bytes) -> list[tuple[int, bytes]]:
        assert index == 0
        seen.append(data)
        return _answer(index, data)

    writer = threading.Thread(target=lambda: [there.sendall(c) for c in chunks])
    try:
        writer.start()
        rest = bytearray()
        n, why, err = core.answer_frames(
            here.fileno(), -1, time.monotonic() + 30.0, ENC_ID, 1, 6, on_frame, rest, threading.Lock()
        )
        writer.join(10)
        assert not writer.is_alive()
        here.setblocking(False)
        while True:
            try:
                more = here.recv(1 << 16)
            except BlockingIOError:
                break
            rest += more
        there.setblocking(False)
        answers = b""
        while True:
            try:
                answers += there.recv(1 << 16)
            except BlockingIOError:
                break
    finally:
        here.close()
        there.close()
    assert (n, why, err) == (plain, AnswerEnd.PYTHON, 0)
    assert seen == [r[16:22] for r in plain_recs]
    assert answers == b"".join(_rec(TORQUE_ID, _torque(d)) for d in seen)
    assert bytes(rest) == stream[len(b"".join(plain_recs)) :]


def test_a_signal_during_the_wait_runs_its_handler_and_hands_back() -> None:
    """A drive's SIGTERM handler sets its stop event: the loop hands back as soon as the handler
    ran (the node's loop then looks at the event), long before its deadline; a handler that raises
    (Ctrl-C's KeyboardInterrupt) raises out of the loop."""
    core = member_core()
    assert core is not None
    ran: list[int] = []
    here, there = socket.socketpair()
    done = threading.Event()

    def poke() -> None:  # until the loop has handed back: a signal sent before it waits is handled before it
        while not done.wait(0.01):
            os.kill(os.getpid(), signal.SIGUSR1)

    def handler(signum: int, _frame: object) -> None:
        ran.append(signum)

    previous = signal.signal(signal.SIGUSR1, handler)
    poker = threading.Thread(target=poke)
    try:
        poker.start()
        deadline = time.monotonic() + 60.0
        n, why, err = core.answer_frames(here.fileno(), -1, deadline, ENC_ID, 1, 6, _answer, bytearray(), threading.Lock())
        assert (n, why, err) == (0, AnswerEnd.DEADLINE, 0) and ran and time.monotonic() < deadline

        def interrupt(signum: int, _frame: object) -> None:
            if not done.is_set():  # once: the pokes still on their way find nothing to raise
                done.set()
                raise KeyboardInterrupt

        signal.signal(signal.SIGUSR1, interrupt)
        with pytest.raises(KeyboardInterrupt):
            core.answer_frames(here.fileno(), -1, time.monotonic() + 60.0, ENC_ID, 1, 6, _answer, bytearray(), threading.Lock())
    finally:
        done.set()
        poker.join(10)
        signal.signal(signal.SIGUSR1, previous)
        here.close()
        there.close()


# ------------------------------------------------------------------ HubBus.answer_frames on a hub


@pytest.fixture
def hub(hub_data_plane: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[HubServer]:
    """A hub of either data plane; the clients of the test answer in C (the client's own switch
    is the same environment variable, set back for them)."""
    with serving_in(tmp_path, hub_data_plane) as server:
        monkeypatch.delenv(HUB_CORE_ENV)
        yield server


def _bus(server: HubServer, name: str) -> HubBus:
    return HubBus(f"{server.addresses[0]}#{name}")


def _enc(k: int) -> can.Message:
    return io_frames.encode_encoder(ENC_ID - io_frames.ENCODER_COB_BASE, k, 1000 + k)


def test_each_way_the_loop_returns_leaves_the_client_reading_in_order(hub: HubServer) -> None:
    with _bus(hub, "io") as drive, _bus(hub, "io") as plant, _bus(hub, "fb") as fb, _bus(hub, "fb") as master:
        assert isinstance(drive, FrameAnswerer) and frame_answerer(drive) == drive.answer_frames
        seen: list[bytes] = []

        def answer(index: int, data: bytes) -> list[tuple[int, bytes]]:
            seen.append(data)
            return _answer(index, data)

        # deadline: nothing came
        assert drive.answer_frames(ENC_ID, 1, 6, answer, time.monotonic() + 0.01, fb.fileno()) == (0, AnswerEnd.DEADLINE)
        # three encoder frames, a control frame, one more (one write of the hub): three answered
        plant.send_batch([_enc(0), _enc(1), _enc(2), io_frames.encode_control(io_frames.IoControlCommand.TRIAL_STOP, 3), _enc(3)])
        assert drive.answer_frames(ENC_ID, 1, 6, answer, time.monotonic() + 5.0, fb.fileno()) == (3, AnswerEnd.PYTHON)
        answers = []
        while len(answers) < 3:
            msg = plant.recv(5.0)
            assert msg is not None
            answers.append((msg.arbitration_id, bytes(msg.data)))
        assert answers == [(TORQUE_ID, _torque(struct.pack("<iH", 1000 + k, k))) for k in range(3)]
        assert seen == [struct.pack("<iH", 1000 + k, k) for k in range(3)]
        first = drive.recv(5.0)
        assert first is not None and first.arbitration_id == io_frames.CONTROL_COB_ID
        # what waits in the client is never skipped: the loop hands it back at once
        assert drive.answer_frames(ENC_ID, 1, 6, answer, time.monotonic() + 5.0, fb.fileno()) == (0, AnswerEnd.PYTHON)
        last = drive.recv(5.0)
        assert last is not None and io_frames.encoder_fields(last) == (1003, 3)
        # the other descriptor: a fieldbus frame waiting comes first
        master.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        assert drive.answer_frames(ENC_ID, 1, 6, answer, time.monotonic() + 5.0, fb.fileno()) == (0, AnswerEnd.OTHER)
        assert fb.recv(5.0) is not None
        # the callable handles its frame itself: stopped, the frames behind it wait in order
        plant.send_batch([_enc(10), _enc(11)])
        n, why = drive.answer_frames(ENC_ID, 1, 6, lambda i, d: None, time.monotonic() + 5.0, fb.fileno())
        assert (n, why) == (1, AnswerEnd.STOPPED)
        nxt = drive.recv(5.0)
        assert nxt is not None and io_frames.encoder_fields(nxt) == (1011, 11)
        # an exception in the callable goes to the caller; the frames behind it still wait
        plant.send_batch([_enc(20), _enc(21)])

        def fail(index: int, data: bytes) -> list[tuple[int, bytes]]:
            raise RuntimeError("the tick failed")

        with pytest.raises(RuntimeError, match="the tick failed"):
            drive.answer_frames(ENC_ID, 1, 6, fail, time.monotonic() + 5.0, fb.fileno())
        nxt = drive.recv(5.0)
        assert nxt is not None and io_frames.encoder_fields(nxt) == (1021, 21)


def test_a_hub_gone_mid_loop_is_the_next_reads_error(
    hub_data_plane: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with serving_in(tmp_path, hub_data_plane) as server:
        monkeypatch.delenv(HUB_CORE_ENV)
        drive = _bus(server, "io")
    try:  # the hub closed: the loop returns, and the client's own read says what happened
        n, why = drive.answer_frames(ENC_ID, 1, 6, _answer, time.monotonic() + 5.0)
        assert (n, why) == (0, AnswerEnd.CLOSED)
        with pytest.raises(can.CanOperationError, match="closed the connection"):
            drive.recv(1.0)
    finally:
        drive.shutdown()
    with pytest.raises(can.CanOperationError, match="closed bus"):
        drive.answer_frames(ENC_ID, 1, 6, _answer, time.monotonic() + 5.0)


def test_a_deadline_that_is_no_time_is_refused_and_one_at_infinity_waits_for_frames(hub: HubServer) -> None:
    with _bus(hub, "io") as drive, _bus(hub, "io") as plant:
        with pytest.raises(ValueError, match="not a number"):
            drive.answer_frames(ENC_ID, 1, 6, _answer, math.nan)
        plant.send_batch([_enc(0), io_frames.encode_control(io_frames.IoControlCommand.TRIAL_STOP, 1)])
        assert drive.answer_frames(ENC_ID, 1, 6, _answer, math.inf) == (1, AnswerEnd.PYTHON)


def test_switched_off_a_client_answers_nothing(hub: HubServer, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(HUB_CORE_ENV, "python")
    with _bus(hub, "io") as drive:
        assert not drive.answers_in_c and frame_answerer(drive) is None
        assert drive.answer_frames(ENC_ID, 1, 6, _answer, time.monotonic() + 5.0) == (0, AnswerEnd.PYTHON)
    assert frame_answerer(can.Bus(interface="virtual", channel="answer-none")) is None


# ------------------------------------------------------------------ a real drive through a trial


class TrialRun(NamedTuple):
    """What :func:`_trial` saw."""

    torques: list[tuple[int, bytes]]  #: the torque frames (id, data)
    trace: np.ndarray  #: the recorded trace's torques
    answered: int  #: ticks answered in C
    frames_in: int  #: frames the node counted in
    ran_in_c: int  #: ticks the firmware's C core ran (firmware_model/plain_ticks.py)
    state: tuple[Any, ...]  #: the drive's control state, time and trial bookkeeping after it


def playing_drive(
    n_ticks: int, firmware: str = "python", amp: float = 0.2, fe_window: int = -1, offset: int = 0
) -> tuple[Drive, DriveClient]:
    """A drive (node :data:`NODE`) armed to play an ``n_ticks`` cosine move of ``amp`` rad in table
    playback (its feed-forward at most 5 N·m: a short move is steep), with a following-error window
    of ``fe_window`` counts for 2 ms (-1: none) and a homing offset of ``offset`` counts."""
    q, qd, qdd = reference(n_ticks, amp)
    drive = Drive(NODE, firmware=firmware)
    drive.nmt_command(0x01)
    client = DriveClient(drive, NODE)
    client.set_mode(-1)
    client.configure(300.0, 10.0)
    client.load_reference(q, qd)
    client.load_feedforward(np.clip(0.1 * qdd, -5.0, 5.0))
    if fe_window >= 0:
        drive.write_object(Obj.FOLLOWING_ERROR_WINDOW, 0, struct.pack("<I", fe_window))
        drive.write_object(Obj.FOLLOWING_ERROR_TIME_OUT, 0, struct.pack("<H", 2))
    client.enable()
    drive.motion.rehome(offset)  # the position is sat32(count + offset)
    client.arm_trial()
    return drive, client


def _trial(server: HubServer, n_ticks: int, firmware: str = "python") -> TrialRun:
    """A real drive (:func:`playing_drive`) on the hub in a thread of this process, and a toy plant
    written here as the io master: TRIAL_START, then each tick's encoder frame after the last
    torque frame."""
    q, qd, _ = reference(n_ticks)
    drive, client = playing_drive(n_ticks, firmware)
    fieldbus, io, plant = _bus(server, "fb"), _bus(server, "io"), _bus(server, "io")
    node = DriveNode(drive, fieldbus, io)
    node.MAX_WAIT_S = 60.0  # the node serves only when something is due (no heartbeat, no timer): never here
    stop = threading.Event()
    thread = threading.Thread(target=node.run, args=(stop,), daemon=True)
    joint = NODE - 1
    torques: list[tuple[int, bytes]] = []
    try:
        thread.start()
        toy = DoubleIntegrator(q[0], qd[0])
        plant.send(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_START, 0, n_ticks))
        assert wait_for(lambda: drive.plant_trial, 10.0)  # the start frame in a wake-up of its own
        for k in range(n_ticks):
            plant.send(io_frames.encode_encoder(joint, k, toy.counts()))
            msg = plant.recv(5.0)
            assert msg is not None, f"no torque frame for tick {k}"
            torques.append((msg.arbitration_id, bytes(msg.data)))
            toy.step(io_frames.decode_torque(msg).torque_units)
        plant.send(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_STOP, n_ticks))
        assert wait_for(lambda: not drive.plant_trial, 10.0)  # the node took the stop frame too
    finally:
        stop.set()  # and a frame to wake the node, which would otherwise wait out its 60 s
        plant.send(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_STOP, n_ticks + 1))
        thread.join(10)
        for bus in (plant, io, fieldbus):
            bus.shutdown()
    assert not thread.is_alive() and node.bus_error is None
    plain = node._plain
    state = (drive.motion.mode.st.tolist(), drive.time_us, int(drive.trial.state), drive.trial.next_tick, node.frames_out)
    trace = client.read_trace().torque_units
    return TrialRun(torques, trace, node.answered, node.frames_in, 0 if plain is None else plain.ticks, state)


def test_a_drive_through_a_trial_answers_its_plain_ticks_in_c_and_sends_what_it_sends_without(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    n = 301
    monkeypatch.delenv(HUB_CORE_ENV, raising=False)
    with serving_in(tmp_path, "c") as server:
        in_c = _trial(server, n)
    monkeypatch.setenv(HUB_CORE_ENV, "python")
    (tmp_path / "p").mkdir()
    with serving_in(tmp_path / "p", "python") as server:
        in_python = _trial(server, n)
    torques, trace, answered, frames_in = in_c.torques, in_c.trace, in_c.answered, in_c.frames_in
    assert torques == in_python[0] and np.array_equal(trace, in_python[1])
    assert [struct.unpack("<iHB", d)[0] for _, d in torques] == list(trace)
    assert {i for i, _ in torques} == {io_frames.torque_cob_id(NODE - 1)}
    assert in_python[2] == 0
    # every tick after a wake-up that left the service nothing to do: all but tick 0 (the start
    # frame's wake-up is served, and the tick after a service goes the Python way)
    assert answered == n - 1, f"{answered} of {n} ticks answered in C"
    assert frames_in == in_python[3]


# ------------------------------------------------------------------ an outsider at random


class AnswerLoopMachine(RuleBasedStateMachine):
    """A plant at random on a hub: encoder frames of the answering joint and of others, control
    frames, frames of the encoder's id with another length, fieldbus frames, in random batches;
    the reader takes them by turns through the answer loop (its callback answering, handling a
    frame itself, or raising) and through ``recv``. After every step: every frame sent went,
    once and in order, either to the callback or to ``recv``; the plant got exactly the callback's
    answers, in order; nothing else came."""

    def __init__(self) -> None:
        super().__init__()
        self._stack = contextlib.ExitStack()
        folder = Path(self._stack.enter_context(tempfile.TemporaryDirectory(prefix="answer-fsm-")))
        server = self._stack.enter_context(serving(HubServer([f"unix:{folder}/hub.sock"])))
        self.drive = self._stack.enter_context(_bus(server, "io"))
        self.plant = self._stack.enter_context(_bus(server, "io"))
        self.fb = self._stack.enter_context(_bus(server, "fb"))
        self.master = self._stack.enter_context(_bus(server, "fb"))
        self.sent: list[tuple[int, bytes]] = []  # io frames the plant sent, in order
        self.taken: list[tuple[int, bytes]] = []  # the same, as the reader took them
        self.answers: list[tuple[int, bytes]] = []  # what the callback answered
        self.plant_got: list[tuple[int, bytes]] = []  # what the plant received
        self.fieldbus_sent = self.fieldbus_taken = 0
        self.mode = "answer"

    def teardown(self) -> None:
        self._stack.close()

    @rule(
        frames=st.lists(
            st.one_of(
                st.tuples(st.just(ENC_ID), st.integers(-(2**31), 2**31 - 1).map(lambda c: struct.pack("<iH", c, 7))),
                st.tuples(st.sampled_from([0x102, 0x103, io_frames.CONTROL_COB_ID]), st.binary(max_size=8)),
                st.tuples(st.just(ENC_ID), st.binary(max_size=8).filter(lambda b: len(b) != 6)),
            ),
            min_size=1,
            max_size=12,
        )
    )
    def plant_sends(self, frames: list[tuple[int, bytes]]) -> None:
        self.plant.send_batch([can.Message(arbitration_id=i, data=d, is_extended_id=False) for i, d in frames])
        self.sent += frames

    @rule()
    def master_sends(self) -> None:
        self.master.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        self.fieldbus_sent += 1

    @rule(mode=st.sampled_from(["answer", "none", "raise"]))
    def callback_will(self, mode: str) -> None:
        self.mode = mode

    def _on_frame(self, index: int, data: bytes) -> list[tuple[int, bytes]] | None:
        self.taken.append((ENC_ID + index, data))
        if self.mode == "raise":
            raise RuntimeError("the tick failed")
        if self.mode == "none":
            return None
        self.answers.append((TORQUE_ID, data[:4]))
        return [(TORQUE_ID, data[:4])]

    @rule()
    def reader_drains(self) -> None:
        """Until every frame sent was taken: the loop, then recv for what it hands back."""

        def settled() -> bool:
            try:
                n, why = self.drive.answer_frames(ENC_ID, 1, 6, self._on_frame, time.monotonic() + 0.05, self.fb.fileno())
            except RuntimeError:
                pass
            else:
                if why == AnswerEnd.OTHER:
                    while self.fb.recv(0) is not None:
                        self.fieldbus_taken += 1
            while (msg := self.drive.recv(0)) is not None:
                self.taken.append((msg.arbitration_id, bytes(msg.data)))
            return len(self.taken) >= len(self.sent)

        assert wait_for(settled, 10.0)

    @invariant()
    def every_frame_once_in_order(self) -> None:
        assert self.taken == self.sent[: len(self.taken)]
        got = []
        while (msg := self.plant.recv(0.05 if len(got) < len(self.answers) else 0)) is not None:
            got.append((msg.arbitration_id, bytes(msg.data)))
        self.plant_got += got
        assert self.plant_got == self.answers
        assert self.fieldbus_taken <= self.fieldbus_sent


TestAnswerLoopAtRandom = AnswerLoopMachine.TestCase
TestAnswerLoopAtRandom.settings = settings(max_examples=15, stateful_step_count=20, deadline=None)

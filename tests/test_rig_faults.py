"""The host's fault detection without role processes: the pure rules of host/rig/fault_classify.py,
and host/rig/watchdog.py on python-can virtual buses — heartbeats and EMCY frames in, one fault
record, NMT STOP on the bus and the fault hooks out, with no trial running."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import can
import canopen
import pytest

from bus.can_errors import overflow_error_frame
from bus.cia301.emcy import emcy_cob_id, encode_emcy
from bus.cia301.nmt import HeartbeatReport, NmtCommand, NmtState, heartbeat_cob_id
from bus.objects import DRIVE_EDS_PATH, FaultCause
from bus.plant_objects import PLANT_EDS_PATH, PlantFault
from bus.transports.config import FIELDBUS, virtual_transport
from host.experiment.bench import TrialFault
from host.experiment.faults import FaultKind, FaultRecord
from host.nodes.sdo_access import SdoAccess
from host.rig.bus_accounting import BusTimeAccounting
from host.rig.channels import RigChannels
from host.rig.fault_classify import (
    BusError,
    ChannelTrouble,
    EmcyFrame,
    bus_fault,
    channel_fault,
    emcy_fault,
    heartbeat_fault,
    node_name,
)
from host.rig.watchdog import STALL_SETTLE_S, Watchdog

NODES = (1, 2, 3, 4, 32)
_prefix = itertools.count()


# ---------------------------------------------------------------------------------------
# the rules
# ---------------------------------------------------------------------------------------


def test_node_names() -> None:
    assert [node_name(n) for n in (1, 4, 32, 127, 9)] == ["drive1", "drive4", "plant", "host", "node 9"]


def test_emcy_frames_as_faults() -> None:
    # the plant node: a torque frame of drive 3 missing at tick 0x0102
    rec = emcy_fault(EmcyFrame(32, 0xFF00, bytes([PlantFault.TICK_TIMEOUT, 3, 0x02, 0x01]), 10.0, 1e9))
    assert (rec.kind, rec.node, rec.node_id, rec.tick, rec.detected_by) == (FaultKind.FRAME_LOST, "drive3", 3, 258, "plant")
    assert rec.message.startswith("io frame lost or late: no torque frame of drive 3 for tick 258")
    assert (rec.t_detected_mono, rec.t_detected_wall) == (10.0, 1e9)
    # the plant node lost the host's heartbeat
    rec = emcy_fault(EmcyFrame(32, 0xFF00, bytes([PlantFault.HOST_LOST, 0, 0, 0]), 1.0, 2.0))
    assert (rec.kind, rec.node, rec.node_id) == (FaultKind.HOST_LOST, "host", 127)
    # the plant node's fieldbus receiver lost frames at tick 5
    rec = emcy_fault(EmcyFrame(32, 0x8110, bytes([PlantFault.FRAMES_LOST, 0, 5, 0]), 1.0, 2.0))
    assert (rec.kind, rec.node, rec.tick, rec.detected_by) == (FaultKind.FRAME_LOST, "plant", 5, "plant")
    assert rec.message == (
        "fieldbus frames lost in the plant node's receiver (receive overflow) at tick 5 (EMCY 0x8110 of the plant node)"
    )
    # a drive's fieldbus receiver lost frames (cause 8)
    rec = emcy_fault(EmcyFrame(3, 0x8110, bytes([FaultCause.CAN_OVERRUN, 0, 0, 0, 0]), 1.0, 2.0))
    assert (rec.kind, rec.node, rec.detected_by) == (FaultKind.FRAME_LOST, "drive3", "drive3")
    assert rec.message == "fieldbus frames lost in drive3's receiver (receive overflow) (EMCY 0x8110)"
    # a channel monitor heard receive overflows only: frames lost, not damaged; with a CRC error among them: damaged
    rec = channel_fault([ChannelTrouble("io", error_frames=2, first_error_frame_t=0.2, overflows=2, first_overflow_t=0.2)], 1.0)
    assert rec is not None and (rec.kind, rec.node, rec.t_detected_mono) == (FaultKind.FRAME_LOST, "io", 0.2)
    assert rec.message == "frames lost on io: a receiver's queue overflowed (receive-overflow error frame)"
    rec = channel_fault([ChannelTrouble("io", error_frames=2, first_error_frame_t=0.1, overflows=1, first_overflow_t=0.2)], 1.0)
    assert rec is not None and (rec.kind, rec.message) == (FaultKind.FRAME_ERROR, "a damaged frame on io (bus error frame)")
    # a drive: the host lost, an io tick out of sequence, a following error
    rec = emcy_fault(EmcyFrame(2, 0x8130, b"", 1.0, 2.0))
    assert (rec.kind, rec.node, rec.detected_by) == (FaultKind.HOST_LOST, "host", "drive2")
    rec = emcy_fault(EmcyFrame(4, 0x8200, bytes([0, 7, 0, 9, 0]), 1.0, 2.0))
    assert (rec.kind, rec.node, rec.tick) == (FaultKind.FRAME_SEQUENCE, "drive4", 7)
    assert rec.message == "io tick out of sequence at drive4: expected tick 7, got 9 (EMCY 0x8200)"
    rec = emcy_fault(EmcyFrame(1, 0x8611, b"", 1.0, 2.0))
    assert (rec.kind, rec.message) == (FaultKind.EMCY, "following error of drive1 (EMCY 0x8611)")
    # an EMCY of the plant node without one of its fault codes (e.g. --inject emcy:plant@1:150):
    # no tick in it, so none is made up (the run places it where its io channel was), not tick 0
    rec = emcy_fault(EmcyFrame(32, 0x8611, bytes([0, 1, 0, 0, 0]), 1.0, 2.0))
    assert (rec.kind, rec.node, rec.tick) == (FaultKind.EMCY, "plant", None)
    assert rec.message == "fault (EMCY 0x8611 of the plant node)"


def test_heartbeat_rules() -> None:
    heard = {n: 9.9 for n in NODES}
    kw = {"consumer_s": 0.5, "period_s": 0.2, "bus_name": "hub"}
    assert heartbeat_fault(HeartbeatReport(), heard, 10.0, **kw) is None
    # one drive silent while the others beat: that node is lost, 600 ms silent, 400 ms after its beat was due
    rec = heartbeat_fault(HeartbeatReport(overdue=[3]), heard | {3: 9.4}, 10.0, **kw)
    assert rec is not None and (rec.kind, rec.node, rec.node_id) == (FaultKind.NODE_LOST, "drive3", 3)
    assert "silent for 600 ms" in rec.message and rec.latency_ms == pytest.approx(400.0)
    # the plant and a drive overdue: the drive is named
    rec = heartbeat_fault(HeartbeatReport(overdue=[2, 32]), heard, 10.0, **kw)
    assert rec is not None and rec.node == "drive2"
    # nobody heard for more than a period: the bus is silent
    rec = heartbeat_fault(HeartbeatReport(overdue=[1]), {n: 9.7 for n in NODES}, 10.0, **kw)
    assert rec is not None and (rec.kind, rec.node) == (FaultKind.BUS_SILENT, "hub")
    # a boot-up during the run
    rec = heartbeat_fault(HeartbeatReport(booted=[4]), heard, 10.0, **kw)
    assert rec is not None and rec.kind == FaultKind.NODE_LOST and "booted again" in rec.message


def test_bus_and_channel_rules() -> None:
    assert bus_fault([], "hub", 1.0) is None
    rec = bus_fault([BusError("io", "OSError: gone", 0.5), BusError("fieldbus", "x", 0.7)], "hub", 1.0)
    assert rec is not None and (rec.kind, rec.node, rec.t_detected_mono) == (FaultKind.BUS_LOST, "hub", 0.5)
    assert rec.message == "the bus is gone (io: OSError: gone)"
    assert channel_fault([], 1.0) is None
    # the first channel's error frames come before the second channel's full disk
    rec = channel_fault(
        [ChannelTrouble("fieldbus", error_frames=2, first_error_frame_t=0.2), ChannelTrouble("io", "No space", 0.1, True)], 1.0
    )
    assert rec is not None and (rec.kind, rec.node) == (FaultKind.FRAME_ERROR, "fieldbus")
    rec = channel_fault([ChannelTrouble("io", "No space left on device", 0.1, True, error_frames=1)], 1.0)
    assert rec is not None and rec.kind == FaultKind.DISK_FULL
    assert rec.message == "disk full: the io.log candump log stopped (No space left on device)"


# ---------------------------------------------------------------------------------------
# the watchdog on virtual buses
# ---------------------------------------------------------------------------------------


@dataclass
class Rig:
    watchdog: Watchdog
    peer: can.BusABC  # the nodes' side of the fieldbus
    declared: list[FaultRecord]


@pytest.fixture
def rig() -> Iterator[Rig]:
    """A watchdog on a virtual fieldbus, its thread not started: the tests run its rounds with the
    times they choose (consumer time 50 ms, heartbeat period 20 ms: ``scale`` 0.1)."""
    tc = virtual_transport(prefix=f"watchdog-test-{next(_prefix)}")
    bus_time = BusTimeAccounting(ts_s=0.001, trial_s=0.3, heartbeat_ms=200, n_nodes=6)
    channels = RigChannels(tc, None, bus_time)
    network = canopen.Network(tc.open(FIELDBUS))
    peer = tc.open(FIELDBUS)
    watchdog = Watchdog(network, channels, bus_name="virtual", out_dir=None, scale=0.1)
    network.listeners.append(watchdog.fieldbus_errors)
    network.connect()
    for nid in NODES:
        node = network.add_node(nid, str(DRIVE_EDS_PATH if nid != 32 else PLANT_EDS_PATH))
        watchdog.events.listen_to(nid, node)
        watchdog.events.watch(nid)
    declared: list[FaultRecord] = []
    watchdog.on_fault(declared.append)
    try:
        yield Rig(watchdog, peer, declared)
    finally:
        watchdog.stop()
        channels.close()
        network.disconnect()
        peer.shutdown()


def beat(rig: Rig, nodes: tuple[int, ...]) -> dict[int, float]:
    """Heartbeats (OPERATIONAL) of ``nodes`` from the peer; returns when the host heard them all."""
    before = rig.watchdog.events.last_heard()
    for nid in nodes:
        rig.peer.send(can.Message(arbitration_id=heartbeat_cob_id(nid), data=[NmtState.OPERATIONAL], is_extended_id=False))
    while True:
        heard = rig.watchdog.events.last_heard()
        if all(heard[n] is not None and heard[n] != before[n] for n in nodes):
            return {n: t for n, t in heard.items() if t is not None}
        time.sleep(0.005)


def emcy_heard(rig: Rig, node_id: int, code: int, register: int) -> None:
    """An EMCY of ``node_id`` from the peer; returns when the host heard it."""
    before = len(rig.watchdog.events.emcy)
    rig.peer.send(can.Message(arbitration_id=emcy_cob_id(node_id), data=encode_emcy(code, register), is_extended_id=False))
    while len(rig.watchdog.events.emcy) == before:
        time.sleep(0.005)


def nmt_stop_seen(peer: can.BusABC, timeout_s: float = 30.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        msg = peer.recv(left)
        if msg is not None and msg.arbitration_id == 0 and bytes(msg.data) == bytes([NmtCommand.STOP, 0]):
            return True
    return False


def test_a_node_lost_outside_a_trial_is_declared_once_with_nmt_stop(rig: Rig) -> None:
    t3 = beat(rig, NODES)[3]
    others = (1, 2, 4, 32)
    while min(beat(rig, others)[n] for n in others) <= t3 + 0.05:  # drive 3 falls silent
        pass
    heard = rig.watchdog.events.last_heard()
    now = min(heard[n] for n in others) + 0.011  # drive 3 silent > 50 ms, the others heard < 24 ms ago
    assert rig.watchdog.detect(now) is None  # not armed yet
    rig.watchdog.arm()  # no trial runs: heartbeats are judged all the same
    assert not rig.watchdog.in_trial
    rec = rig.watchdog.detect(now)
    assert rec is not None
    assert (rec.kind, rec.node, rec.node_id, rec.detected_by) == (FaultKind.NODE_LOST, "drive3", 3, "host")
    rig.watchdog.declare(rec)
    assert nmt_stop_seen(rig.peer)  # torque off everywhere
    assert rig.declared == [rec] and rig.watchdog.fault is rec
    assert (rec.trial, rec.tick) == (0, None)  # the next trial; no tick on the io channel
    with pytest.raises(TrialFault) as exc:
        rig.watchdog.raise_if_fault()
    assert exc.value.record is rec
    rig.watchdog.declare(FaultRecord(FaultKind.EMCY, "a second fault"))  # the first fault stays the fault
    assert rig.declared == [rec] and rig.watchdog.detect(now) is None


def test_an_emcy_is_declared_and_logged(rig: Rig) -> None:
    beat(rig, NODES)
    rig.watchdog.arm()
    emcy_heard(rig, 2, 0x8611, 0x01)
    rig.watchdog.watch_round()
    assert len(rig.declared) == 1
    rec = rig.declared[0]
    assert (rec.kind, rec.node, rec.detected_by) == (FaultKind.EMCY, "drive2", "drive2")
    assert rec.message == "following error of drive2 (EMCY 0x8611)"
    assert [(e["node"], e["code"], e["register"]) for e in rig.watchdog.events.emcy] == [(2, 0x8611, 0x01)]
    assert nmt_stop_seen(rig.peer)


def test_lost_nodes_tolerated_between_trials_but_not_during_one(rig: Rig) -> None:
    beat(rig, NODES)
    rig.watchdog.tolerate_lost_between_trials = True  # --recover
    rig.watchdog.arm()
    later = time.monotonic() + 10.0  # every node silent by then
    assert rig.watchdog.detect(later) is None
    with rig.watchdog.during_trial(1):
        assert rig.watchdog.in_trial and rig.watchdog.trial == 1
        rec = rig.watchdog.detect(later)
    assert not rig.watchdog.in_trial
    assert rec is not None and (rec.kind, rec.node) == (FaultKind.BUS_SILENT, "virtual")
    assert rec.message == "no heartbeat from any node for 50 ms: the bus is silent (virtual stalled?)"


def test_a_bus_error_frame_while_the_boot_ups_are_awaited_ends_the_wait_at_once(rig: Rig) -> None:
    """Not armed yet (the bring-up awaits the nodes' boot-ups): heartbeats are not judged, but a bus
    error frame heard (a lost datagram, which may have been a boot-up) is the run's fault at once:
    declared with NMT STOP and raised, not a boot-up awaited until the host's ``--wait`` runs out."""
    rig.watchdog.raise_if_start_fault()  # all is well: nothing declared, nothing raised
    assert rig.declared == []
    rig.peer.send(can.Message(is_error_frame=True, arbitration_id=0x20000080, is_extended_id=True, data=bytes(8)))
    rec: FaultRecord | None = None
    deadline = time.monotonic() + 30.0
    while rec is None and time.monotonic() < deadline:  # until the channel's monitor has heard it
        try:
            rig.watchdog.raise_if_start_fault()
        except TrialFault as exc:
            rec = exc.record
        time.sleep(0.005)
    assert rec is not None and rig.declared == [rec] and (rec.kind, rec.node) == (FaultKind.FRAME_ERROR, "fieldbus")
    assert nmt_stop_seen(rig.peer)


def start_fault(rig: Rig) -> FaultRecord:
    """The fault :meth:`Watchdog.raise_if_start_fault` raises once what the host heard got through
    (a frame from the peer takes the notifier's thread)."""
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        try:
            rig.watchdog.raise_if_start_fault()
        except TrialFault as exc:
            assert exc.record is not None
            return exc.record
        time.sleep(0.005)
    raise AssertionError("no fault raised within 30 s")


def test_a_frame_the_hosts_own_receiver_lost_while_the_boot_ups_are_awaited_ends_the_wait_at_once(rig: Rig) -> None:
    """The canopen network's receiver overflowed (udp_multicast: the kernel dropped a datagram on
    the host's socket, maybe the boot-up awaited) while the channel monitors' receivers kept every
    frame: a fault of the fieldbus at once, not a boot-up awaited until ``--wait`` runs out."""
    rig.watchdog.raise_if_start_fault()
    rig.watchdog.fieldbus_errors.on_message_received(overflow_error_frame(time.time(), FIELDBUS))  # as the notifier hands it
    rec = start_fault(rig)
    assert rig.declared == [rec] and (rec.kind, rec.node, rec.detected_by) == (FaultKind.FRAME_LOST, "fieldbus", "host")
    assert rec.message == "frames lost on fieldbus: a receiver's queue overflowed (receive-overflow error frame)"
    assert rig.watchdog.channels.troubles() == []  # the monitors heard nothing wrong
    assert nmt_stop_seen(rig.peer)


def test_a_nodes_emcy_while_the_boot_ups_are_awaited_ends_the_wait_at_once(rig: Rig) -> None:
    """A drive whose receiver lost the NMT reset says so with EMCY 0x8110 and never boots again:
    its EMCY ends the host's wait for the boot-ups as the run's fault at once."""
    emcy_heard(rig, 4, 0x8110, 0x11)
    rec = start_fault(rig)
    assert rig.declared == [rec] and (rec.kind, rec.node) == (FaultKind.EMCY, "drive4")
    assert "EMCY 0x8110" in rec.message
    assert nmt_stop_seen(rig.peer)


@pytest.mark.parametrize("when", ["starting", "disarmed", "stopped"])
def test_an_emcy_is_declared_while_the_nodes_are_brought_up_never_after_the_watchdog_stood_down(rig: Rig, when: str) -> None:
    """Before the first ``arm`` (the nodes being brought up) the watchdog's own rounds declare a
    node's EMCY (heartbeats are not judged yet); once disarmed or stopped at the run's close they
    declare nothing, whatever was heard."""
    if when == "disarmed":
        rig.watchdog.arm()
        rig.watchdog.disarm()
    elif when == "stopped":
        rig.watchdog.stop()
    later = time.monotonic() + 10.0  # every node's heartbeat overdue by then
    assert rig.watchdog.detect(later) is None
    emcy_heard(rig, 3, 0x8110, 0x11)
    rig.watchdog.watch_round()
    if when == "starting":
        assert len(rig.declared) == 1 and (rig.declared[0].kind, rig.declared[0].node) == (FaultKind.EMCY, "drive3")
        assert nmt_stop_seen(rig.peer)
    else:
        assert rig.declared == [] and rig.watchdog.detect(later) is None


def _upload_in_thread(node: canopen.RemoteNode) -> tuple[threading.Thread, list[BaseException]]:
    """``node.sdo.upload(0x1000, 0)`` (canopen's own API, as the bring-up's probe) in a thread; the
    list gets what it raised."""
    raised: list[BaseException] = []

    def upload() -> None:
        try:
            node.sdo.upload(0x1000, 0)
        except BaseException as exc:  # noqa: BLE001 - the test looks at it
            raised.append(exc)

    thread = threading.Thread(target=upload, daemon=True)
    thread.start()
    return thread, raised


def test_a_fault_ends_the_hosts_sdo_requests_waiting_and_to_come(rig: Rig) -> None:
    """The fault hook cancels every node's SDO access: a request waiting for a node that never
    answers ends at once (the wake), and one made afterwards on canopen's own API (the bring-up's
    probe) is not sent into a 60 s wait either (canopen empties its response queue when a request
    begins, so the wake alone would miss it)."""
    network = rig.watchdog.network
    node = network.add_node(5, str(DRIVE_EDS_PATH))  # nobody answers for node 5
    node.sdo.RESPONSE_TIMEOUT = 60.0
    access = SdoAccess(node)
    waiting, raised = _upload_in_thread(node)
    assert rig.peer.recv(10.0) is not None  # the request is on the bus: the thread waits for the answer
    access.cancel("the run stopped")
    waiting.join(10.0)
    assert not waiting.is_alive() and isinstance(raised[0], canopen.SdoAbortedError)
    later, raised_later = _upload_in_thread(node)
    later.join(10.0)
    assert not later.is_alive() and isinstance(raised_later[0], canopen.SdoCommunicationError)


def test_the_launchers_liveness_watch_hears_a_node_from_its_first_heartbeat_to_its_next_boot_up() -> None:
    """:meth:`host.rig.liveness.LivenessWatch.heard` (the launcher's short grace for a node that
    dies before the host hears it, tests/test_launcher.py): not before a heartbeat, not after a
    boot-up (the host awaits it then)."""
    from host.rig.liveness import LivenessWatch

    watch = LivenessWatch(virtual_transport(prefix=f"liveness-test-{next(_prefix)}"))  # not started: frames fed in

    def frame(state: int) -> can.Message:
        return can.Message(arbitration_id=heartbeat_cob_id(2), data=[state], is_extended_id=False)

    assert not watch.heard(2)
    watch._heard(frame(NmtState.BOOT_UP), 1.0)
    assert not watch.heard(2)
    watch._heard(frame(NmtState.PRE_OPERATIONAL), 1.2)
    assert watch.heard(2) and not watch.heard(3)
    watch._heard(frame(NmtState.BOOT_UP), 1.4)
    assert not watch.heard(2)


class _HostGap:
    """The host's heartbeat producer as the watchdog asks it (:meth:`HostHeartbeat.take_gap`): the
    gap between two of its beats that the test sets, taken once."""

    error: str | None = None
    error_t: float | None = None

    def __init__(self) -> None:
        self.gap: tuple[float, float] | None = None

    def take_gap(self, longer_than_s: float, since: float | None = None) -> tuple[float, float] | None:
        gap, self.gap = self.gap, None
        return gap if gap is not None and gap[0] > longer_than_s else None


def test_a_host_gap_no_node_reports_is_kept_while_they_consume_it_and_a_fault_once_they_are_stopped(rig: Rig) -> None:
    """The host did not run for 0.9 s and no node's EMCY 0x8130 came: while the nodes consume its
    heartbeat (operational), they did not run either (the whole machine stopped) -- kept in
    ``stalls``, not declared; once they are NMT STOPPED (the shutdown) they report no loss, and the
    same gap is the host's fault."""
    watchdog, producer = rig.watchdog, _HostGap()
    watchdog.producer = producer  # type: ignore[assignment]
    watchdog.tolerate_lost_between_trials = True  # the nodes' heartbeats are not the question here
    watchdog.arm()
    now = time.monotonic()
    producer.gap = (0.9, now)
    assert watchdog.detect(now) is None  # the nodes' EMCYs may still come
    settled = STALL_SETTLE_S + 0.001  # (now + 0.2) - now may round to below 0.2 s
    assert watchdog.detect(now + settled) is None and not rig.declared
    (stall,) = watchdog.stalls
    assert (stall["gap_ms"], stall["trial"], stall["in_trial"]) == (900.0, 0, False)
    assert stall["what"] == (
        "the host did not run for 900 ms (before trial 0) and no node reported losing its heartbeat: "
        "the nodes did not run either (the whole machine was stopped); not a fault"
    )
    watchdog.stopped_at = now + 1.5
    producer.gap = (0.9, now + 2.0)  # began before the NMT STOP
    assert watchdog.detect(now + 2.0) is None
    rec = watchdog.detect(now + 2.0 + settled)
    assert rec is not None and (rec.kind, rec.node, rec.detected_by) == (FaultKind.HOST_LOST, "host", "host")
    assert rec.message.startswith("the host did not run for 900 ms (it was stopped)") and len(watchdog.stalls) == 1


def test_a_watchdog_round_that_raises_is_the_runs_fault_never_a_thread_that_ends_unseen(
    rig: Rig, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    beat(rig, NODES)
    rig.watchdog.arm()

    def broken(now: float) -> FaultRecord | None:
        raise RuntimeError("a detector's bug")

    monkeypatch.setattr(rig.watchdog, "detect", broken)
    declared = threading.Event()
    rig.watchdog.on_fault(lambda _record: declared.set())
    with caplog.at_level("ERROR", logger="host.rig.watchdog"):
        rig.watchdog.start()
        assert declared.wait(30.0)
    rec = rig.watchdog.fault
    assert rec is not None and rig.declared == [rec]
    assert (rec.kind, rec.node, rec.detected_by) == (FaultKind.TRIAL_FAULT, "host", "host")
    assert rec.message.startswith("the host's watchdog failed (RuntimeError: a detector's bug): the run was no longer watched")
    assert nmt_stop_seen(rig.peer)  # torque off everywhere, as for any fault
    assert any("a detector's bug" in (r.exc_text or "") or r.exc_info for r in caplog.records)  # where, in the host's log
    with pytest.raises(TrialFault):
        rig.watchdog.raise_if_fault()


def test_a_round_after_the_watchdog_did_not_run_waits_for_the_grace_of_the_round_that_saw_it(
    rig: Rig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two threads judge (the watchdog's and the trial loop's ``watch_round``). After the host did
    not run for seconds (a law's call holding the GIL), the first round sees the gap and counts every
    node as heard; a second round that comes while that grace waits (for the notifier, which reads
    the heartbeats queued meanwhile) must not judge the heartbeats of before the gap -- it would find
    the first node the notifier had not read yet lost ("heartbeat of drive3 lost (silent for 7719
    ms)" after a 7 s call, drives 1 and 2 read already). The rounds' times are given: the host stood
    still for 10 s."""
    t = max(beat(rig, NODES).values())
    rig.watchdog.arm()
    rig.watchdog._round(t)  # a round just after the nodes were heard: all well
    assert rig.declared == []
    real_grace = rig.watchdog.events.grace
    entered, go = threading.Event(), threading.Event()

    def slow_grace(now: float) -> None:
        entered.set()
        go.wait(30.0)
        real_grace(now)

    monkeypatch.setattr(rig.watchdog.events, "grace", slow_grace)
    first = threading.Thread(target=rig.watchdog._round, args=(t + 10.0,))  # 10 s without a round: the gap
    first.start()
    assert entered.wait(30.0)
    second = threading.Thread(target=rig.watchdog._round, args=(t + 10.01,))
    second.start()
    second.join(0.5)  # the second round may not judge before the grace: it waits for it
    go.set()
    first.join(30.0)
    second.join(30.0)
    assert rig.declared == []  # every node counted as heard at t + 10 s, judged from there

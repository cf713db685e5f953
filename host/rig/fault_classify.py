"""What a fault seen by the host is: pure functions from an observation to one
:class:`host.experiment.faults.FaultRecord`.

This module owns the host's fault vocabulary on the bus, without threads, locks or frames:

* :func:`node_name` — ``drive1`` … ``drive4``, ``plant``, ``host`` for a node id;
* :func:`bus_fault` — a failing bus (the fieldbus, a monitor's bus, the host's heartbeat send);
* :func:`channel_fault` — a channel's candump log stopped (full disk, failing write) or a bus error
  frame on it;
* :func:`emcy_fault` — the fault an EMCY frame reports (codes: docs/canopen-objects.md §3);
* :func:`heartbeat_fault` — overdue or rebooted nodes: one node lost, or the whole bus silent;
* :func:`plant_trial_fault` / :func:`sdo_fault` — the record of an exception the trial loop caught
  (the plant node's fault state, an SDO request refused, unanswered or cancelled).

Times are ``time.monotonic()`` seconds (``t_mono``) or ``time.time()`` seconds (``t_wall``);
latencies are in ms. Every record gets a node and a detection latency measured on the detector's
own clock (what it waited for before it could tell: a consumer time past the heartbeat that was
due, a tick deadline, an SDO timeout; 0 for what is seen as it happens — an EMCY, a bus error frame,
an SDO abort, a failing write); an injection that caused the fault replaces it later with the time
since the injection (:func:`host.experiment.faults.attach_injection`).
:class:`host.rig.watchdog.Watchdog` gathers the observations and calls these in a fixed order.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from bus.cia301.nmt import CONSUMER_TIME_MS, HOST_NODE_ID, NODE_HEARTBEAT_MS, HeartbeatReport
from bus.errors import SdoAbort
from bus.io_frames import TICK_TIMEOUT_S
from bus.objects import DRIVE_NODE_IDS, FaultCause
from bus.pil_fault import pil_target_fault
from bus.plant_objects import DEFAULT_PLANT_NODE_ID as PLANT_NODE_ID
from bus.plant_objects import PlantFault
from host.experiment.faults import FaultKind, FaultRecord, node_name
from host.nodes.plant_client import PlantTrialFault
from host.nodes.sdo_access import SdoTransportError

__all__ = [
    "BusError",
    "ChannelTrouble",
    "DetectionTimes",
    "EmcyFrame",
    "bus_fault",
    "channel_fault",
    "emcy_fault",
    "heartbeat_fault",
    "node_name",
    "host_stall_fault",
    "plant_trial_fault",
    "sdo_fault",
    "with_wall_time",
]


@dataclass(frozen=True)
class DetectionTimes:
    """What the detectors wait for before they can tell, s (× ``ILCRIG_TIMEOUT_SCALE``).

    :ivar consumer_s: a heartbeat consumer's time (the host's and the nodes')
    :ivar period_s: the heartbeat period of the nodes and of the host
    :ivar tick_deadline_s: the plant's deadline for a tick's torque frames
    """

    consumer_s: float = CONSUMER_TIME_MS / 1000.0
    period_s: float = NODE_HEARTBEAT_MS / 1000.0
    tick_deadline_s: float = TICK_TIMEOUT_S

    @classmethod
    def scaled(cls, scale: float) -> DetectionTimes:
        return cls(cls.consumer_s * scale, cls.period_s * scale, cls.tick_deadline_s * scale)

    @property
    def lost_heartbeat_ms(self) -> float:
        """From the heartbeat that was due to the consumer's verdict, ms."""
        return 1000.0 * max(self.consumer_s - self.period_s, 0.0)


#: EMCY error codes the drives send (docs/canopen-objects.md §3)
EMCY_HOST_LOST = 0x8130
EMCY_TICK_SEQUENCE = 0x8200
EMCY_CAN_OVERRUN = 0x8110
EMCY_FOLLOWING_ERROR = 0x8611

#: the plant node's fault codes as fault kinds
PLANT_FAULT_KINDS: Mapping[PlantFault, FaultKind] = {
    PlantFault.PLANT: FaultKind.PLANT_ERROR,
    PlantFault.TICK_TIMEOUT: FaultKind.FRAME_LOST,
    PlantFault.TICK_SEQUENCE: FaultKind.FRAME_SEQUENCE,
    PlantFault.BAD_FRAME: FaultKind.FRAME_ERROR,
    PlantFault.HOST_LOST: FaultKind.HOST_LOST,
    PlantFault.ABORTED: FaultKind.TRIAL_FAULT,
    PlantFault.FRAMES_LOST: FaultKind.FRAME_LOST,
    PlantFault.IO_FRAMES_LOST: FaultKind.FRAME_LOST,
}


@dataclass(frozen=True)
class BusError:
    """A bus that failed: its channel, the error text and when it was seen (``t_mono``, s)."""

    channel: str
    error: str
    t_mono: float | None


@dataclass(frozen=True)
class ChannelTrouble:
    """What a channel monitor noted: its log stopped (``log_error``, on a full disk
    ``disk_full``) and the bus error frames it saw (``error_frames``, the first at
    ``first_error_frame_t``), ``overflows`` of them receive overflows (frames lost in a receiver's
    full queue, :func:`bus.can_errors.is_receive_overflow`; the first at ``first_overflow_t``), the
    rest damaged frames."""

    channel: str
    log_error: str | None = None
    log_error_t: float | None = None
    disk_full: bool = False
    error_frames: int = 0
    first_error_frame_t: float | None = None
    overflows: int = 0
    first_overflow_t: float | None = None


@dataclass(frozen=True)
class EmcyFrame:
    """An EMCY frame with an error code (not an error reset): its node, code, data and when the
    node sent it (``t_mono`` / ``t_wall``, s)."""

    node_id: int
    code: int
    data: bytes
    t_mono: float
    t_wall: float


def bus_fault(errors: Sequence[BusError], bus_name: str, now: float) -> FaultRecord | None:
    """The first failing bus of ``errors`` as a ``bus_lost`` fault (``bus_name``: ``hub`` or the
    transport's name), None if there is none."""
    if not errors:
        return None
    err = errors[0]
    return FaultRecord(
        FaultKind.BUS_LOST,
        f"the bus is gone ({err.channel}: {err.error})",
        node=bus_name,
        detected_by="host",
        t_detected_mono=err.t_mono or now,
        latency_ms=0.0,
        latency_basis="bus error",
    )


def channel_fault(channels: Sequence[ChannelTrouble], now: float) -> FaultRecord | None:
    """The first channel in trouble: a stopped log (``disk_full`` / ``output_error``) before its
    error frames (``frame_lost`` when every one of them was a receive overflow, else
    ``frame_error``: a damaged frame); None if all are well."""
    for ch in channels:
        if ch.log_error is not None:
            kind = FaultKind.DISK_FULL if ch.disk_full else FaultKind.OUTPUT_ERROR
            what = "disk full" if ch.disk_full else "cannot write"
            return FaultRecord(
                kind,
                f"{what}: the {ch.channel}.log candump log stopped ({ch.log_error})",
                node="host",
                detected_by="host",
                t_detected_mono=ch.log_error_t or now,
                latency_ms=0.0,
                latency_basis="failed write",
            )
        if ch.error_frames:
            lost = ch.overflows == ch.error_frames  # receive overflows only: frames lost, none damaged
            return FaultRecord(
                FaultKind.FRAME_LOST if lost else FaultKind.FRAME_ERROR,
                f"frames lost on {ch.channel}: a receiver's queue overflowed (receive-overflow error frame)"
                if lost
                else f"a damaged frame on {ch.channel} (bus error frame)",
                node=ch.channel,
                detected_by="host",
                t_detected_mono=(ch.first_overflow_t if lost else ch.first_error_frame_t) or now,
                latency_ms=0.0,
                latency_basis="bus error frame",
            )
    return None


def _plant_latency(fault: PlantFault, times: DetectionTimes) -> tuple[float, str]:
    """How long the plant node waited before it could tell ``fault``: its tick deadline for a
    missing frame, its consumer time for a lost host, else nothing (seen as it happened)."""
    if fault == PlantFault.TICK_TIMEOUT:
        return 1000.0 * times.tick_deadline_s, "the plant's tick deadline"
    if fault == PlantFault.HOST_LOST:
        return times.lost_heartbeat_ms, "its next heartbeat was due"
    return 0.0, "the plant saw it"


def _plant_emcy_fault(frame: EmcyFrame, data: bytes, times: DetectionTimes) -> FaultRecord:
    """The plant node's EMCY: data[0] its fault code, data[1] the drive, data[2:4] the tick. An
    EMCY without one of the plant's fault codes (data[0] 0 or unknown: not the plant's own report
    of a stopped trial) carries no tick: the record's tick is left unknown (None), so the run
    places it where its io channel was (:func:`host.experiment.fault_placement.place`), never at 0."""
    try:
        fault = PlantFault(data[0])
    except ValueError:
        fault = PlantFault.NONE
    drive = data[1] if fault != PlantFault.NONE else 0
    tick: int | None = int.from_bytes(data[2:4], "little") if fault != PlantFault.NONE else None
    texts = {
        PlantFault.PLANT: f"plant error at tick {tick}",
        PlantFault.TICK_TIMEOUT: f"io frame lost or late: no torque frame of drive {drive} for tick {tick} within the deadline",
        PlantFault.TICK_SEQUENCE: f"io frame out of sequence (duplicated, stale or skipped) from drive {drive} at tick {tick}",
        PlantFault.BAD_FRAME: (
            f"malformed torque frame of drive {drive} at tick {tick}"
            if drive
            else f"damaged io frame (bus error frame) at tick {tick}"
        ),
        PlantFault.HOST_LOST: "the host's heartbeat was lost",
        PlantFault.FRAMES_LOST: f"fieldbus frames lost in the plant node's receiver (receive overflow) at tick {tick}",
        PlantFault.IO_FRAMES_LOST: f"io frames lost in the plant node's receiver (receive overflow) at tick {tick}",
        PlantFault.ABORTED: f"the plant node aborted the trial at tick {tick}",
    }
    node = f"drive{drive}" if drive else ("host" if fault == PlantFault.HOST_LOST else "plant")
    latency, basis = _plant_latency(fault, times)
    return FaultRecord(
        PLANT_FAULT_KINDS.get(fault, FaultKind.EMCY),
        f"{texts.get(fault, 'fault')} (EMCY 0x{frame.code:04X} of the plant node)",
        node=node,
        node_id=drive or (HOST_NODE_ID if fault == PlantFault.HOST_LOST else PLANT_NODE_ID),
        tick=tick,
        detected_by="plant",
        t_detected_mono=frame.t_mono,
        t_detected_wall=frame.t_wall,
        latency_ms=latency,
        latency_basis=basis,
    )


def emcy_fault(frame: EmcyFrame, times: DetectionTimes | None = None) -> FaultRecord:
    """The fault an EMCY frame reports (codes: docs/canopen-objects.md §3); ``times``: what the
    nodes wait for before they report (default: unscaled)."""
    times = times or DetectionTimes()
    data = frame.data + bytes(8)
    if frame.node_id == PLANT_NODE_ID:
        return _plant_emcy_fault(frame, data, times)
    name = node_name(frame.node_id)
    if frame.code == EMCY_HOST_LOST:
        return FaultRecord(
            FaultKind.HOST_LOST,
            f"the host's heartbeat was lost (EMCY 0x8130 of {name})",
            node="host",
            node_id=HOST_NODE_ID,
            detected_by=name,
            t_detected_mono=frame.t_mono,
            t_detected_wall=frame.t_wall,
            latency_ms=times.lost_heartbeat_ms,
            latency_basis="its next heartbeat was due",
        )
    if frame.code == EMCY_TICK_SEQUENCE:
        expected, got = int.from_bytes(data[1:3], "little"), int.from_bytes(data[3:5], "little")
        return _own_report(
            FaultKind.FRAME_SEQUENCE,
            f"io tick out of sequence at {name}: expected tick {expected}, got {got} (EMCY 0x8200)",
            frame,
            "the frame's arrival",
            tick=expected,
        )
    if frame.code == EMCY_CAN_OVERRUN and data[0] == FaultCause.CAN_OVERRUN:
        return _own_report(
            FaultKind.FRAME_LOST,
            f"fieldbus frames lost in {name}'s receiver (receive overflow) (EMCY 0x8110)",
            frame,
            "the loss's error frame",
        )
    if frame.code == EMCY_CAN_OVERRUN and data[0] == FaultCause.IO_FRAMES_LOST:
        next_tick = int.from_bytes(data[1:3], "little")
        return _own_report(
            FaultKind.FRAME_LOST,
            f"io frames lost in {name}'s receiver (receive overflow) before tick {next_tick} (EMCY 0x8110)",
            frame,
            "the loss's error frame",
            tick=next_tick,
        )
    pil = pil_target_fault(frame.code, frame.data)
    if pil is not None:  # the drive's PIL target failed (EMCY 0x6100, cause 9)
        text, tick = pil
        return _own_report(FaultKind.EMCY, f"{text} (internal error of {name}, EMCY 0x6100)", frame, "the node's report", tick)
    what = "following error" if frame.code == EMCY_FOLLOWING_ERROR else "fault"
    return _own_report(FaultKind.EMCY, f"{what} of {name} (EMCY 0x{frame.code:04X})", frame, "the node's report")


def _own_report(kind: FaultKind, message: str, frame: EmcyFrame, basis: str, tick: int | None = None) -> FaultRecord:
    """A fault the drive that sent ``frame`` reports of itself: detected by it when the EMCY came
    (latency 0, measured from ``basis``)."""
    name = node_name(frame.node_id)
    return FaultRecord(
        kind,
        message,
        node=name,
        node_id=frame.node_id,
        tick=tick,
        detected_by=name,
        t_detected_mono=frame.t_mono,
        t_detected_wall=frame.t_wall,
        latency_ms=0.0,
        latency_basis=basis,
    )


def host_stall_fault(gap_s: float, t_end: float, times: DetectionTimes) -> FaultRecord:
    """The host itself did not run for ``gap_s`` seconds (it was stopped), ending at ``t_end``
    (``t_mono``): longer than the nodes' consumer time of its heartbeat — a fault even where no
    node's EMCY 0x8130 says so (a node reports nothing when NMT STOPPED, and its consumer starts
    with the first heartbeat after it was configured)."""
    return FaultRecord(
        FaultKind.HOST_LOST,
        f"the host did not run for {1000 * gap_s:.0f} ms (it was stopped): longer than the nodes' consumer time of its heartbeat",
        node="host",
        node_id=HOST_NODE_ID,
        detected_by="host",
        t_detected_mono=t_end,
        latency_ms=max(1000.0 * gap_s - 1000.0 * times.period_s, 0.0),
        latency_basis="its heartbeat was due",
    )


def heartbeat_fault(
    report: HeartbeatReport,
    last_heard: Mapping[int, float | None],
    now: float,
    *,
    consumer_s: float,
    period_s: float,
    bus_name: str,
) -> FaultRecord | None:
    """The fault a heartbeat check shows, None if every node beats and none booted again.

    :param last_heard: when each of the five nodes was last heard (``t_mono``, s; None: never)
    :param consumer_s: the host's consumer time, s
    :param period_s: the nodes' heartbeat period, s
    :param bus_name: what to blame when no node is heard at all (``hub`` or the transport)
    """
    if report.overdue:
        everyone = set(DRIVE_NODE_IDS) | {PLANT_NODE_ID}
        quiet = 1.2 * period_s  # > a period: every node missed a beat
        heard = [last_heard.get(n) for n in everyone]
        if set(report.overdue) >= everyone or all(t is None or now - t > quiet for t in heard):
            last = max((t for t in heard if t is not None), default=None)
            return FaultRecord(
                FaultKind.BUS_SILENT,
                f"no heartbeat from any node for {1000 * consumer_s:.0f} ms: the bus is silent ({bus_name} stalled?)",
                node=bus_name,
                detected_by="host",
                t_detected_mono=now,
                latency_ms=1000 * max(now - last - period_s, 0.0) if last is not None else 1000 * consumer_s,
                latency_basis="the heartbeats were due",
            )
        nid = sorted(report.overdue, key=lambda n: (n == PLANT_NODE_ID, n))[0]
        seen = last_heard.get(nid)
        silent = f"{1000 * (now - seen):.0f} ms" if seen is not None else "ever"
        return _node_lost(
            nid,
            f"heartbeat of {node_name(nid)} lost (silent for {silent}: the process died or stalled)",
            now,
            latency_ms=1000 * (now - seen - period_s) if seen else None,
            latency_basis="its next heartbeat was due" if seen else None,
        )
    if report.booted:
        nid = report.booted[0]
        return _node_lost(
            nid,
            f"{node_name(nid)} booted again during the run (it was reset or restarted)",
            now,
            latency_ms=0.0,
            latency_basis="its boot-up frame",
        )
    return None


def _node_lost(nid: int, message: str, now: float, *, latency_ms: float | None, latency_basis: str | None) -> FaultRecord:
    """A ``node_lost`` fault of node ``nid`` the host detected at ``now`` (``t_mono``, s)."""
    return FaultRecord(
        FaultKind.NODE_LOST,
        message,
        node=node_name(nid),
        node_id=nid,
        detected_by="host",
        t_detected_mono=now,
        latency_ms=latency_ms,
        latency_basis=latency_basis,
    )


def plant_trial_fault(exc: PlantTrialFault, trial: int, now: float, times: DetectionTimes | None = None) -> FaultRecord:
    """The plant node's fault state read back after a trial ended in fault."""
    st = exc.state
    latency, basis = _plant_latency(st.fault, times or DetectionTimes())
    return FaultRecord(
        PLANT_FAULT_KINDS.get(st.fault, FaultKind.TRIAL_FAULT),
        f"plant node: {st.describe()}",
        node=f"drive{st.fault_node}" if st.fault_node else "plant",
        node_id=st.fault_node or PLANT_NODE_ID,
        trial=trial,
        tick=st.fault_tick,
        detected_by="plant",
        t_detected_mono=now,
        latency_ms=latency,
        latency_basis=basis,
    )


def sdo_fault(exc: SdoTransportError | SdoAbort, trial: int, now: float) -> FaultRecord:
    """An SDO request refused (abort), unanswered or cancelled, as an ``sdo_error``: the latency is
    how long the request waited for its answer (an abort: 0)."""
    nid = getattr(exc, "node_id", None)
    waited = exc.elapsed_s if isinstance(exc, SdoTransportError) else None
    timed_out = isinstance(exc, SdoTransportError) and not exc.cancelled and waited is not None
    return FaultRecord(
        FaultKind.SDO_ERROR,
        str(exc),
        node=node_name(nid) if nid else "host",
        node_id=nid,
        trial=trial,
        detected_by="host",
        t_detected_mono=now,
        latency_ms=1000.0 * waited if timed_out and waited is not None else 0.0,
        latency_basis="the SDO request (no answer)" if timed_out else "the SDO answer",
    )


def with_wall_time(record: FaultRecord) -> FaultRecord:
    """``record`` with both detection times: ``t_detected_wall`` from ``t_detected_mono`` (one
    machine: the wall clock's offset from CLOCK_MONOTONIC now), or both now when neither is known.
    Returns ``record``."""
    if record.t_detected_wall is None:
        now_mono, now_wall = time.monotonic(), time.time()
        if record.t_detected_mono is None:
            record.t_detected_mono = now_mono
        record.t_detected_wall = now_wall - (now_mono - record.t_detected_mono)
    return record

"""CiA 301 network management: NMT command frames, node states, heartbeat frames and a
host-side heartbeat consumer.  Pure codecs and state; no I/O, no clock (time is passed in).

* NMT command: COB-ID 0x000, 2 bytes ``[cs, node_id]``; node id 0 addresses all nodes.
* Heartbeat / boot-up: COB-ID ``0x700 + node_id``, 1 byte = node state (bit 7 is the node
  guarding toggle bit and is ignored on decode).
* Heartbeat consumer entries (object 0x1016, CiA 301 §7.5.2.3): U32 ``node_id << 16 | time_ms``;
  :class:`NodeHeartbeatConsumer` is a node's consumer, :class:`HeartbeatConsumer` the host's.

The heartbeat timing of the rig is defined here, once (both sides must agree):

* :data:`HOST_NODE_ID` — the host (NMT master) is node **127** on the fieldbus; it produces its
  heartbeat on COB-ID ``0x77F`` every :data:`HOST_HEARTBEAT_MS`;
* the nodes (drives 1–4, plant node 32) produce theirs every :data:`NODE_HEARTBEAT_MS`
  (the host writes it to 0x1017);
* every consumer — the nodes consuming the host (0x1016, written by the host) and the host
  consuming the nodes — declares a producer lost after :data:`CONSUMER_TIME_MS`
  (2.5 producer periods; × ``ILCRIG_TIMEOUT_SCALE``), so a lost producer is noticed within
  3 heartbeat periods;
* a consumer that did not run itself for half its shortest consumer time (its process, or the whole
  machine, stopped) judges no producer for that time: it reads what came meanwhile, then counts the
  producers as heard (the host's watchdog and the launcher's liveness watch alike; a node:
  :meth:`NodeHeartbeatConsumer.grace`).  A freeze of the whole machine is no lost host.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from enum import IntEnum

from bus.run_queue import RECHECK_S, RunQueueLedger

logger = logging.getLogger(__name__)

#: COB-ID of NMT commands.
NMT_COB_ID = 0x000
#: COB-ID base of heartbeat / boot-up frames.
HEARTBEAT_BASE = 0x700
#: Node id 0 in an NMT command: every node.
ALL_NODES = 0
#: The host's (NMT master's) node id on the fieldbus; its heartbeat COB-ID is 0x77F.
HOST_NODE_ID = 0x7F
#: Producer heartbeat period of the host, ms.
HOST_HEARTBEAT_MS = 200
#: Producer heartbeat period the host gives every node (object 0x1017), ms.
NODE_HEARTBEAT_MS = 200
#: Consumer heartbeat time of every consumer (nodes: object 0x1016; host), ms, before
#: ``ILCRIG_TIMEOUT_SCALE``: 2.5 producer periods.
CONSUMER_TIME_MS = 500
#: Object index of the consumer heartbeat time (ARRAY of U32 ``node_id << 16 | time_ms``).
CONSUMER_HEARTBEAT_INDEX = 0x1016


class NmtFrameError(ValueError):
    """A frame is not a valid NMT command or heartbeat."""


class NmtCommand(IntEnum):
    """NMT command specifiers (byte 0 of an NMT command frame)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """Node states as encoded in the heartbeat byte."""

    BOOT_UP = 0x00  # the boot-up message
    INITIALISING = 0x00  # alias of BOOT_UP (the state's name in CiA 301 / bus.objects)
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


def _check_node_id(node_id: int, allow_all: bool = False) -> None:
    low = 0 if allow_all else 1
    if not low <= node_id <= 127:
        raise NmtFrameError(f"node id must be {low}..127, got {node_id}")


def heartbeat_cob_id(node_id: int) -> int:
    """COB-ID of node ``node_id``'s heartbeat (``0x700 + node_id``)."""
    _check_node_id(node_id)
    return HEARTBEAT_BASE + node_id


def encode_nmt(command: int, node_id: int = ALL_NODES) -> bytes:
    """Data bytes of an NMT command frame (COB-ID 0).

    :param command: NMT command specifier (:class:`NmtCommand`).
    :param node_id: target node 1..127, or 0 for all nodes.
    :raises NmtFrameError: unknown command or node id out of range.
    """
    try:
        cs = NmtCommand(command)
    except ValueError:
        raise NmtFrameError(f"unknown NMT command specifier 0x{command:02X}") from None
    _check_node_id(node_id, allow_all=True)
    return bytes([cs, node_id])


def decode_nmt(data: bytes) -> tuple[NmtCommand, int]:
    """Decode NMT command frame data into ``(command, node_id)`` (node id 0 = all).

    :raises NmtFrameError: wrong length, unknown command or node id > 127.
    """
    if len(data) != 2:
        raise NmtFrameError(f"NMT command frame must have 2 data bytes, got {len(data)}")
    try:
        cs = NmtCommand(data[0])
    except ValueError:
        raise NmtFrameError(f"unknown NMT command specifier 0x{data[0]:02X}") from None
    _check_node_id(data[1], allow_all=True)
    return cs, data[1]


def nmt_addresses(data: bytes, node_id: int) -> NmtCommand | None:
    """The command of NMT frame ``data`` if it addresses ``node_id`` (directly or all), else None.

    :raises NmtFrameError: malformed frame.
    """
    cs, target = decode_nmt(data)
    return cs if target in (ALL_NODES, node_id) else None


def next_state(state: NmtState, command: NmtCommand) -> NmtState:
    """NMT slave state after ``command`` (CiA 301 fig. 48).

    The resets return :attr:`NmtState.PRE_OPERATIONAL`, the state a node reaches after its
    reset and boot-up message (the caller sends the boot-up frame).
    """
    if command is NmtCommand.START:
        return NmtState.OPERATIONAL
    if command is NmtCommand.STOP:
        return NmtState.STOPPED
    if command is NmtCommand.ENTER_PRE_OPERATIONAL:
        return NmtState.PRE_OPERATIONAL
    return NmtState.PRE_OPERATIONAL  # RESET_NODE / RESET_COMMUNICATION, after boot-up


def encode_heartbeat(state: int) -> bytes:
    """Data byte of a heartbeat (or boot-up, state 0) frame.

    :raises NmtFrameError: state not one of :class:`NmtState`.
    """
    try:
        return bytes([NmtState(state)])
    except ValueError:
        raise NmtFrameError(f"not a heartbeat state: 0x{state:02X}") from None


def decode_heartbeat(data: bytes) -> NmtState:
    """Decode heartbeat frame data (1 byte; the toggle bit 7 is ignored).

    :raises NmtFrameError: wrong length or unknown state.
    """
    if len(data) != 1:
        raise NmtFrameError(f"heartbeat frame must have 1 data byte, got {len(data)}")
    try:
        return NmtState(data[0] & 0x7F)
    except ValueError:
        raise NmtFrameError(f"not a heartbeat state: 0x{data[0]:02X}") from None


def heartbeat_node_id(cob_id: int) -> int | None:
    """Node id if ``cob_id`` is a heartbeat COB-ID (0x701..0x77F), else None."""
    node_id = cob_id - HEARTBEAT_BASE
    return node_id if 1 <= node_id <= 127 else None


@dataclass
class HeartbeatReport:
    """Result of :meth:`HeartbeatConsumer.report_at`.

    :ivar overdue: nodes whose heartbeat is late (sorted).
    :ivar booted: nodes that sent a boot-up since the previous check (in arrival order).
    :ivar states: the last state heard from each node.
    """

    overdue: list[int] = field(default_factory=list)
    booted: list[int] = field(default_factory=list)
    states: dict[int, NmtState] = field(default_factory=dict)


class HeartbeatConsumer:
    """Host-side heartbeat monitor (CiA 301 heartbeat consumer, like object 0x1016).

    Pure: feed received heartbeats with :meth:`on_heartbeat` and ask :meth:`report_at` with the
    current time [s].  A monitored node is overdue when nothing was heard from it for longer
    than its timeout; a node never heard is overdue ``timeout`` after monitoring started
    (the first time passed in after :meth:`watch`).

    :param timeouts_s: consumer timeout per node id [s] (typically 1.5–3 × the producer period).
    :param ledger: the waits for a CPU of the processes that carry the heartbeats (the hub,
        :mod:`bus.run_queue`): a silence they explain is not overdue, the node is judged from then on
    """

    def __init__(self, timeouts_s: dict[int, float] | None = None, ledger: RunQueueLedger | None = None) -> None:
        self.ledger = ledger
        self._timeouts_s: dict[int, float] = {}
        self._last_s: dict[int, float | None] = {}
        self._states: dict[int, NmtState] = {}
        self._booted: list[int] = []
        for node_id, timeout_s in (timeouts_s or {}).items():
            self.watch(node_id, timeout_s)

    def watch(self, node_id: int, timeout_s: float) -> None:
        """Monitor ``node_id`` with consumer timeout ``timeout_s`` [s] (> 0)."""
        _check_node_id(node_id)
        if not timeout_s > 0:
            raise ValueError(f"heartbeat timeout must be > 0 s, got {timeout_s}")
        self._timeouts_s[node_id] = float(timeout_s)
        self._last_s.setdefault(node_id, None)

    def on_heartbeat(self, node_id: int, data: bytes, now_s: float) -> NmtState:
        """Record a heartbeat frame from ``node_id`` received at ``now_s`` [s].

        :raises NmtFrameError: malformed heartbeat data.
        """
        state = decode_heartbeat(data)
        if state is NmtState.BOOT_UP:
            logger.info("node %d booted", node_id)
            self._booted.append(node_id)
        self._states[node_id] = state
        self._last_s[node_id] = now_s
        if self.ledger is not None:
            self.ledger.heard(node_id)
        return state

    def on_frame(self, cob_id: int, data: bytes, now_s: float) -> NmtState | None:
        """Convenience: record ``data`` if ``cob_id`` is a heartbeat COB-ID; else return None."""
        node_id = heartbeat_node_id(cob_id)
        if node_id is None:
            return None
        return self.on_heartbeat(node_id, data, now_s)

    def state(self, node_id: int) -> NmtState | None:
        """Last state heard from ``node_id`` (None if never heard)."""
        return self._states.get(node_id)

    def last_heard(self, node_id: int) -> float | None:
        """When ``node_id`` was last heard [s] (None if never)."""
        return self._last_s.get(node_id)

    def grace(self, now_s: float) -> None:
        """Count every monitored node as heard at ``now_s``: after the consumer itself could not
        run (its process was stopped), the frames queued meanwhile are still to be read."""
        for node_id in self._timeouts_s:
            self._last_s[node_id] = now_s
            if self.ledger is not None:
                self.ledger.heard(node_id)

    def timeout(self, node_id: int) -> float | None:
        """The consumer timeout of ``node_id`` [s] (None if not monitored)."""
        return self._timeouts_s.get(node_id)

    def report_at(self, now_s: float) -> HeartbeatReport:
        """Overdue monitored nodes at ``now_s`` [s], and the boot-ups since the last check."""
        overdue = []
        for node_id, timeout_s in self._timeouts_s.items():
            last = self._last_s.get(node_id)
            if last is None:
                self._last_s[node_id] = last = now_s  # monitoring starts now
            if now_s - last > timeout_s:
                excuse = None if self.ledger is None else self.ledger.judge(node_id, now_s - last, timeout_s)
                if excuse is None:
                    overdue.append(node_id)
                elif not excuse.pending:  # else its carrier waits for a CPU now: the next report judges
                    self._last_s[node_id] = now_s  # its carrier waited for a CPU: judged from now
        booted, self._booted = self._booted, []
        return HeartbeatReport(sorted(overdue), booted, dict(self._states))


def consumer_entry(node_id: int, time_ms: int) -> int:
    """A 0x1016 sub-entry: ``node_id << 16 | time_ms`` (time 0 or node 0 = entry unused).

    :raises NmtFrameError: node id outside 0..127 or time outside 0..65535 ms.
    """
    if not 0 <= node_id <= 127:
        raise NmtFrameError(f"node id must be 0..127, got {node_id}")
    if not 0 <= time_ms <= 0xFFFF:
        raise NmtFrameError(f"consumer time must be 0..65535 ms, got {time_ms}")
    return (int(node_id) << 16) | int(time_ms)


def decode_consumer_entry(value: int) -> tuple[int, int] | None:
    """``(node_id, time_ms)`` of a 0x1016 sub-entry, or None when the entry is unused
    (node id 0 or > 127, or time 0)."""
    node_id, time_ms = (int(value) >> 16) & 0xFF, int(value) & 0xFFFF
    if not 1 <= node_id <= 127 or time_ms == 0:
        return None
    return node_id, time_ms


class NodeHeartbeatConsumer:
    """A node's heartbeat consumer (CiA 301, object 0x1016), pure (time is passed in).

    Monitoring of a producer starts with the first heartbeat (or boot-up) received from it after
    it was configured; when nothing more arrives for its consumer time the producer is reported
    lost once by :meth:`expired`; the next heartbeat from it arms the monitoring again.  With a
    ``ledger`` (:class:`bus.run_queue.RunQueueLedger`: the processes that carry the heartbeats,
    the hub) a silence explained by their wait for a CPU is no loss: the producer is judged from
    then on (logged).
    """

    def __init__(self, ledger: RunQueueLedger | None = None) -> None:
        #: the carriers' waits for a CPU (None: every silence is the producer's)
        self.ledger = ledger
        #: the producers to judge again at ``_recheck_s``: their carrier waits for a CPU now
        self._rechecking: set[int] = set()
        self._recheck_s = 0.0
        self._time_s: dict[int, float] = {}
        self._last_s: dict[int, float] = {}
        #: earliest loss time [s] of the armed producers (None: none armed); asked every loop of
        #: the node, so kept up to date on each change instead of recomputed
        self._due_s: float | None = None
        #: half the shortest consumer time, s (inf: none configured): a node woken this much past
        #: the time it asked for did not run meanwhile (:meth:`grace`)
        self.stall_s = math.inf

    def _update_due(self) -> None:
        due = [last + self._time_s[n] for n, last in self._last_s.items() if n not in self._rechecking]
        if self._rechecking:
            due.append(self._recheck_s)
        self._due_s = min(due) if due else None

    @property
    def producers(self) -> dict[int, float]:
        """Monitored node id → consumer time, s."""
        return dict(self._time_s)

    def configure(self, entries: dict[int, float]) -> None:
        """Monitor exactly ``entries`` (node id → consumer time, s); a producer whose entry is
        unchanged keeps its state, a new or changed one waits for its first heartbeat."""
        for node_id in list(self._time_s):
            if entries.get(node_id) != self._time_s[node_id]:
                del self._time_s[node_id]
                self._last_s.pop(node_id, None)
        for node_id, time_s in entries.items():
            if time_s > 0:
                self._time_s[node_id] = float(time_s)
        self.stall_s = min(self._time_s.values()) / 2 if self._time_s else math.inf
        self._update_due()

    def grace(self, now_s: float) -> None:
        """Count every armed producer as heard at ``now_s``: the node itself did not run for longer
        than :attr:`stall_s` (its process, or the whole machine, was stopped). What a producer sent
        meanwhile was read before this; a producer stopped with it (the same machine) cannot have
        been heard -- it gets a consumer time from now, as after its first heartbeat."""
        for node_id in self._last_s:
            self._last_s[node_id] = now_s
            if self.ledger is not None:
                self.ledger.heard(node_id)
        self._rechecking.clear()
        self._update_due()

    def after_stall(self, node_id: int, due_s: float, now_s: float) -> None:
        """Node ``node_id`` ran again at ``now_s``, more than :attr:`stall_s` after a wake-up due at
        ``due_s`` (it did not run meanwhile): :meth:`grace`, said in its log -- never a producer
        lost for the node's own stall."""
        logger.info(
            "node %d: ran again %.0f ms after its wake-up was due: heartbeats judged from now", node_id, 1e3 * (now_s - due_s)
        )
        self.grace(now_s)

    def on_heartbeat(self, node_id: int, now_s: float) -> None:
        """A heartbeat (or boot-up) frame of ``node_id`` arrived at ``now_s``."""
        if node_id in self._time_s:
            self._last_s[node_id] = now_s
            self._rechecking.discard(node_id)
            self._update_due()
            if self.ledger is not None:
                self.ledger.heard(node_id)

    def next_deadline(self) -> float | None:
        """Earliest time [s] at which a monitored producer becomes lost (None: none armed)."""
        return self._due_s

    def expired(self, now_s: float) -> list[int]:
        """Producers lost at ``now_s`` (each reported once per loss, sorted)."""
        if self._due_s is None or now_s < self._due_s - 1e-9:  # margin: the exact test is below
            return []
        lost = sorted(n for n, last in self._last_s.items() if now_s - last >= self._time_s[n])
        self._rechecking.clear()
        for n in list(lost):
            excuse = None if self.ledger is None else self.ledger.judge(n, now_s - self._last_s[n], self._time_s[n])
            if excuse is None:
                del self._last_s[n]  # disarmed until its next heartbeat
                continue
            lost.remove(n)
            if excuse.pending:  # its carrier waits for a CPU now: judged again soon
                self._rechecking.add(n)
                self._recheck_s = now_s + RECHECK_S
            else:
                self._last_s[n] = now_s  # its carrier waited for a CPU: judged from now
        self._update_due()
        return lost

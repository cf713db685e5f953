"""Fault injection for ``ilcrig run --inject SPEC``: the spec language and the hub's frame faults.

This module owns the grammar of an injection (:func:`parse_spec`), the record every injector
writes when it injects (one JSON line in ``RUN_DIR/logs/injections-<who>.jsonl``:
:func:`write_record`), and :class:`FrameFaultInjector`, the hook the hub calls for every frame it
forwards (:class:`bus.transports.hub.server.HubServer`'s ``frame_hook``).  Killing, stalling and
spoofed EMCY frames are done by the launcher (:mod:`host.rig.inject`), which owns the processes.

Grammar::

    SPEC  := ACTION ':' TARGET ['@' WHEN] (',' KEY '=' VALUE)*
           | 'diskfull' ['@' WHEN]
    WHEN  := TRIAL [':' TICK]         in trial TRIAL at tick TICK
           | TRIAL ':end'             after trial TRIAL (between it and the next; after the last)
           | 'before'                 before the first trial (once the host has started the nodes)
           | 'after'                  after the last trial (while the host ends the run)

=============================  ===========================================================================
``kill:ROLE@T:N``              SIGKILL ``ROLE`` (``host``, ``plant``, ``hub``, ``drive1`` … ``drive4``) when
                               the plant sends tick N of trial T
``stall:ROLE@T:N,for=S``       SIGSTOP it there for S seconds (default 2), then SIGCONT
``drop:CHAN@T:N``              lose frames on ``CHAN`` (``io`` or ``fieldbus``) from tick N of trial T on
``corrupt:CHAN@T:N``           damage frames on the wire: like a CAN controller every receiver sees a
                               CRC error — a bus error frame — instead, and the frame is lost
``overflow:CHAN@T:N``          lose frames in the receivers' full queues: every receiver gets the
                               receive-overflow error frame a CAN controller (SocketCAN
                               CAN_ERR_CRTL_RX_OVERFLOW) or udp_multicast's dropped datagram gives
                               instead, and the frame is lost
``duplicate:CHAN@T:N``         deliver frames twice
``delay:CHAN@T:N,ms=D``        deliver frames D ms late (default twice the plant's tick deadline
                               :data:`bus.io_frames.TICK_TIMEOUT_S` × scale: a *late* frame; a shorter
                               delay is absorbed by the lockstep)
``emcy:NODE@T:N,code=C``       an EMCY frame as if ``NODE`` (``drive1`` … ``drive4``, ``plant``) sent it
                               (code default 0x8611, a following error)
``diskfull@T``                 the host's writes of the run's outputs fail with ENOSPC from trial T's on
                               (``@T:end`` the same, ``@before`` from the first summary on, ``@after``
                               from the last trial's; ``@T:N``: the channels' candump logs from tick N
                               of trial T on, in the trial)
=============================  ===========================================================================

Where an injection acts (:attr:`FaultSpec.when`): ``tick`` (``@T:N``), ``end`` (``@T:end``),
``before``, ``after``.  What is injected in a trial happens when the plant sends that tick; after
trial T (``@after``: the last trial), when the run's summary holds trial T — for every injector
alike, the hub's frame faults too (:class:`SummaryTrials`: the hub is given the summary's path);
before the first trial, when the host starts the nodes (its first NMT START on the fieldbus).
Whether a spec fits the experiment — a trial and a tick inside it, io frame faults only in a trial
(the io channel carries no frame between trials), a role the transport has — is checked before
anything starts (:func:`check_specs`).

Frame faults (drop, corrupt, overflow, duplicate, delay) take ``rate=P`` (probability per eligible frame,
default 1: the next one), ``seed=K`` (default 0), ``count=C`` (at most C frames, default 1) and
``id=COBID`` (only that COB-ID).  Eligible on ``io``: the encoder and torque frames (the
TRIAL_START/STOP control frames are idempotent commands); on ``fieldbus``: every frame but NMT.
Whether a frame is hit depends only on the seed, the trial, the tick and the COB-ID of the frame
(on the fieldbus: its COB-ID and how many frames of that COB-ID came before it since the trigger),
never on the order in which the hub sees frames: a seed reproduces a run's faults.  Trial T = 0
is the first trial; T and N default to 0.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import struct
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bus import io_frames
from bus.errors import InputError
from bus.units import timeout_scale

logger = logging.getLogger(__name__)

__all__ = [
    "FaultSpec",
    "FaultSpecError",
    "FrameFaultInjector",
    "SummaryTrials",
    "check_specs",
    "parse_spec",
    "parse_specs",
    "write_record",
    "PROCESS_ACTIONS",
    "FRAME_ACTIONS",
    "ROLES",
    "CHANNELS",
]

PROCESS_ACTIONS = ("kill", "stall")
FRAME_ACTIONS = ("drop", "corrupt", "overflow", "duplicate", "delay")
ACTIONS = (*PROCESS_ACTIONS, *FRAME_ACTIONS, "emcy", "diskfull")
ROLES = ("host", "plant", "hub", "drive1", "drive2", "drive3", "drive4")
CHANNELS = ("io", "fieldbus")
EMCY_NODES = ("drive1", "drive2", "drive3", "drive4", "plant")
_KEYS = {
    "kill": set(),
    "stall": {"for"},
    "emcy": {"code"},
    "diskfull": set(),
    **{a: {"rate", "seed", "count", "id", "ms"} for a in FRAME_ACTIONS},
}
#: SocketCAN's error-frame class of a protocol violation (CAN_ERR_PROT) and the location byte of a
#: CRC sequence error (CAN_ERR_PROT_LOC_CRC_SEQ): the error frame a damaged frame causes
_CAN_ERR_PROT = 0x008
_CAN_ERR_PROT_LOC_CRC_SEQ = 0x08


class FaultSpecError(InputError):
    """An ``--inject`` spec is not valid (one line naming it and the allowed form)."""


#: where an injection acts (:attr:`FaultSpec.when`)
WHEN_TICK, WHEN_END, WHEN_BEFORE, WHEN_AFTER = "tick", "end", "before", "after"


@dataclass(frozen=True)
class FaultSpec:
    """One parsed injection (see the module docstring); ``trial``/``tick`` mean something for
    ``when`` = ``tick`` (both) and ``end`` (the trial)."""

    text: str
    action: str
    target: str
    trial: int = 0
    tick: int = 0
    options: dict[str, float] = field(default_factory=dict)
    when: str = WHEN_TICK

    def resolved(self, iterations: int) -> FaultSpec:
        """``after`` as ``end`` of the last of ``iterations`` trials (the same moment)."""
        if self.when != WHEN_AFTER:
            return self
        return FaultSpec(self.text, self.action, self.target, iterations - 1, 0, dict(self.options), WHEN_END)

    @property
    def rate(self) -> float:
        return float(self.options.get("rate", 1.0))

    @property
    def seed(self) -> int:
        return int(self.options.get("seed", 0))

    @property
    def count(self) -> int:
        return int(self.options.get("count", 1))

    @property
    def cob_id(self) -> int | None:
        v = self.options.get("id")
        return None if v is None else int(v)

    @property
    def stall_s(self) -> float:
        return float(self.options.get("for", 2.0))

    @property
    def delay_s(self) -> float:
        ms = self.options.get("ms")
        return 2.0 * io_frames.TICK_TIMEOUT_S * timeout_scale() if ms is None else float(ms) / 1000.0

    @property
    def emcy_code(self) -> int:
        return int(self.options.get("code", 0x8611))

    def as_dict(self) -> dict[str, Any]:
        return {
            "spec": self.text,
            "action": self.action,
            "target": self.target,
            "trial": self.trial,
            "tick": self.tick,
            "when": self.when,
            "options": dict(self.options),
        }


_FORM = (
    "kill|stall:ROLE@WHEN[,for=S], drop|corrupt|overflow|duplicate|delay:io|fieldbus@WHEN"
    "[,rate=P,seed=K,count=C,id=COBID,ms=D], emcy:NODE@WHEN[,code=C] or diskfull@WHEN, "
    "WHEN = TRIAL:TICK, TRIAL:end, before or after"
)


def _number(spec: str, key: str, text: str) -> float:
    try:
        v = float(int(text, 0)) if text.strip().lower().startswith("0x") else float(text)
    except ValueError:
        raise FaultSpecError(f"--inject {spec}: {key}={text!r} is not a number") from None
    if v != v or v in (float("inf"), float("-inf")):
        raise FaultSpecError(f"--inject {spec}: {key} must be finite, got {text}")
    return v


def parse_spec(text: str) -> FaultSpec:
    """One ``--inject`` spec.

    :raises FaultSpecError: one line naming the spec and the allowed form.
    """
    spec = text.strip()
    head, *opts = spec.split(",")
    if "@" not in head:
        raise FaultSpecError(f"--inject {spec}: @WHEN is missing (when the fault acts); the forms are {_FORM}")
    head, where = head.split("@", 1)
    action, _, target = head.partition(":")
    action = action.strip().lower()
    target = target.strip().lower()
    if action not in ACTIONS:
        raise FaultSpecError(f"--inject {spec}: unknown action {action!r}; the forms are {_FORM}")
    if action == "diskfull":
        if target:
            raise FaultSpecError(f"--inject {spec}: diskfull takes no target (diskfull@WHEN)")
    elif action in PROCESS_ACTIONS and target not in ROLES:
        raise FaultSpecError(f"--inject {spec}: {action} needs a role: {', '.join(ROLES)}")
    elif action in FRAME_ACTIONS and target not in CHANNELS:
        raise FaultSpecError(f"--inject {spec}: {action} needs a channel: {', '.join(CHANNELS)}")
    elif action == "emcy" and target not in EMCY_NODES:
        raise FaultSpecError(f"--inject {spec}: emcy needs a node: {', '.join(EMCY_NODES)}")
    when, trial, tick = _parse_when(spec, where.strip().lower(), action)
    options: dict[str, float] = {}
    for opt in opts:
        key, sep, value = opt.partition("=")
        key = key.strip().lower()
        if not sep or key not in _KEYS[action]:
            allowed = ", ".join(sorted(_KEYS[action])) or "none"
            raise FaultSpecError(f"--inject {spec}: option {opt.strip()!r} not known for {action} (options: {allowed})")
        options[key] = _number(spec, key, value)
    if not 0.0 < options.get("rate", 1.0) <= 1.0:
        raise FaultSpecError(f"--inject {spec}: rate must be in (0, 1], got {options['rate']:g}")
    if options.get("count", 1) < 1 or options.get("count", 1) != int(options.get("count", 1)):
        raise FaultSpecError(f"--inject {spec}: count must be an integer >= 1")
    if options.get("seed", 0) < 0 or options.get("seed", 0) != int(options.get("seed", 0)):
        raise FaultSpecError(f"--inject {spec}: seed must be an integer >= 0")
    if not 0.0 < options.get("for", 2.0) <= 3600.0:
        raise FaultSpecError(f"--inject {spec}: for must be in (0, 3600] s")
    if not 0.0 <= options.get("ms", 0.0) <= 600_000.0:
        raise FaultSpecError(f"--inject {spec}: ms must be in [0, 600000]")
    if "id" in options and not 0 <= options["id"] <= 0x7FF:
        raise FaultSpecError(f"--inject {spec}: id must be an 11-bit COB-ID (0..0x7FF)")
    if "code" in options and not 0x0001 <= options["code"] <= 0xFFFF:
        raise FaultSpecError(f"--inject {spec}: code must be an EMCY error code 0x0001..0xFFFF")
    return FaultSpec(spec, action, target, trial, tick, options, when)


def _parse_when(spec: str, where: str, action: str) -> tuple[str, int, int]:
    """(when, trial, tick) of ``@WHEN`` (``diskfull@T``: ``T:end``)."""
    if where in (WHEN_BEFORE, WHEN_AFTER):
        return where, 0, 0
    trial_text, colon, tick_text = where.partition(":")
    if tick_text.strip() == WHEN_END:
        when = WHEN_END
        tick_text = ""
    elif action == "diskfull" and not colon:
        when = WHEN_END  # diskfull@T: from trial T's outputs on
    else:
        when = WHEN_TICK
    try:
        trial = int(trial_text) if trial_text.strip() else 0
        tick = int(tick_text) if tick_text.strip() else 0
    except ValueError:
        raise FaultSpecError(
            f"--inject {spec}: @WHEN must be TRIAL:TICK (two integers >= 0, e.g. @1:150), TRIAL:end, before or after"
        ) from None
    if trial < 0 or tick < 0:
        raise FaultSpecError(f"--inject {spec}: trial and tick must be >= 0")
    return when, trial, tick


def parse_specs(texts: Sequence[str] | None) -> list[FaultSpec]:
    """Every ``--inject`` spec (see :func:`parse_spec`)."""
    return [parse_spec(t) for t in texts or ()]


def check_specs(specs: Sequence[FaultSpec], *, iterations: int, n_ticks: int, hub: bool) -> None:
    """Refuse an injection that cannot happen in a run of ``iterations`` trials of ``n_ticks``
    ticks on a transport with (``hub``) or without a hub: a trial or a tick outside it, an io frame
    fault outside a trial, a frame fault or a hub injection without a hub.

    :raises FaultSpecError: one line naming the spec and what the experiment allows
    """
    for sp in specs:
        if sp.action in FRAME_ACTIONS and not hub:
            raise FaultSpecError(f"--inject {sp.text}: frame faults are done by the hub: use --bus hub")
        if sp.target == "hub" and not hub:
            raise FaultSpecError(f"--inject {sp.text}: this transport has no hub")
        if sp.when in (WHEN_TICK, WHEN_END) and sp.trial >= iterations:
            raise FaultSpecError(
                f"--inject {sp.text}: trial {sp.trial} is beyond the run's {iterations} trial"
                f"{'s' if iterations != 1 else ''} (0..{iterations - 1})"
            )
        if sp.when == WHEN_TICK and sp.tick >= n_ticks:
            raise FaultSpecError(
                f"--inject {sp.text}: tick {sp.tick} is beyond a trial of {n_ticks} ticks (0..{n_ticks - 1}); "
                f"after the trial is @{sp.trial}:end"
            )
        if sp.action in FRAME_ACTIONS and sp.target == "io" and sp.when != WHEN_TICK:
            raise FaultSpecError(
                f"--inject {sp.text}: the io channel carries frames only during a trial: give @TRIAL:TICK "
                "(or a fieldbus frame fault)"
            )


def write_record(path: str | Path | None, record: dict[str, Any]) -> dict[str, Any]:
    """Append one injection record (with ``t_mono`` / ``t_wall`` of now unless given) to the JSON
    lines file ``path``; a failing write is logged, never raised. Returns the record."""
    record.setdefault("t_mono", time.monotonic())
    record.setdefault("t_wall", time.time())
    logger.info("injected %s", record)
    if path is not None:
        try:
            with open(path, "a", encoding="utf-8") as fh:
                fh.write(json.dumps(record) + "\n")
                fh.flush()
        except OSError as err:
            logger.error("cannot write the injection record to %s: %s", path, err)
    return record


class SummaryTrials:
    """How many trials a run's ``summary.json`` holds now: the moment of ``@T:end`` / ``@after``
    (the summary is replaced atomically after every trial). The file is looked at no more often
    than every ``poll_s`` and read again only when it changed; a missing or half-seen file counts
    as what was read last (0 at first).

    :param path: the run's ``summary.json`` (None: never any trial)
    :param poll_s: the least time between two looks, s
    """

    def __init__(self, path: str | Path | None, poll_s: float = 0.002) -> None:
        self.path = None if path is None else Path(path)
        self.poll_s = poll_s
        self._stamp: tuple[int, int] | None = None
        self._kept = 0
        self._next_look = 0.0

    def __call__(self) -> int:
        if self.path is None:
            return 0
        now = time.monotonic()
        if now < self._next_look:
            return self._kept
        self._next_look = now + self.poll_s
        try:
            st = os.stat(self.path)
        except OSError:
            return self._kept
        stamp = (st.st_mtime_ns, st.st_ino)
        if stamp != self._stamp:
            try:
                data = json.loads(self.path.read_text(encoding="utf-8"))
                self._kept = len(data.get("iterations", []))
                self._stamp = stamp
            except (OSError, ValueError, AttributeError, TypeError):
                pass  # replaced meanwhile: read at the next look
        return self._kept


def _unit(seed: int, *parts: int) -> float:
    """A uniform number in [0, 1) from (seed, parts): the same inputs, the same number."""
    digest = hashlib.blake2b(struct.pack(f"<{1 + len(parts)}q", seed, *parts), digest_size=8).digest()
    return int.from_bytes(digest, "little") / 2**64


@dataclass
class _Armed:
    spec: FaultSpec
    hits: int = 0
    seen: dict[int, int] = field(default_factory=dict)  # fieldbus: frames per COB-ID since the trigger


class FrameFaultInjector:
    """The hub's frame-fault hook: for every frame, which records to deliver and when.

    :param specs: the frame faults (other actions are ignored here)
    :param log_path: where the injection records go (JSON lines), or None
    :param io_bus: / :param fieldbus_bus: the logical bus names of the two channels
    """

    def __init__(
        self,
        specs: Sequence[FaultSpec],
        log_path: str | Path | None = None,
        *,
        io_bus: str = "io",
        fieldbus_bus: str = "fieldbus",
        iterations: int | None = None,
        summary: str | Path | None = None,
    ) -> None:
        self.armed = [
            _Armed(s.resolved(iterations) if iterations is not None else s)
            for s in specs
            if s.action in FRAME_ACTIONS and (s.when != WHEN_AFTER or iterations is not None)
        ]
        self.log_path = log_path
        self.buses = {io_bus: "io", fieldbus_bus: "fieldbus"}
        self.follower = io_frames.TrialTickFollower()
        self.injected: list[dict[str, Any]] = []
        #: the host has started the nodes (an NMT START seen on the fieldbus): ``@before`` from now on
        self.started = False
        #: the trials the run's summary holds (``@T:end``, ``@after``)
        self.kept = SummaryTrials(summary)

    @classmethod
    def from_json(cls, text: str) -> FrameFaultInjector:
        """From the hub's ``--inject`` argument: ``{"specs": [...], "log": path, "iterations": K,
        "summary": path}`` (the run's trials, for ``@after``; its summary, for ``@T:end``)."""
        cfg = json.loads(text)
        return cls(
            parse_specs(cfg.get("specs", [])), cfg.get("log"), iterations=cfg.get("iterations"), summary=cfg.get("summary")
        )

    def _reached(self, spec: FaultSpec, tick: int | None) -> bool:
        f = self.follower
        if spec.when == WHEN_BEFORE:
            return self.started
        if spec.when == WHEN_END:
            return self.kept() > spec.trial  # when the summary holds trial T (not when the plant ends it)
        if f.trial > spec.trial:
            return True
        return f.trial == spec.trial and tick is not None and tick >= spec.tick

    def deliveries(
        self,
        bus: str,
        record: bytes,
        can_id: int,
        data: bytes,
        is_error: bool = False,
    ) -> list[tuple[float, bytes]]:
        """``[(delay_s, record)]`` to deliver for one frame on logical bus ``bus``: ``[]`` drops it,
        two entries duplicate it, a bus error frame replaces a damaged one, a delay holds it."""
        channel = self.buses.get(bus)
        if channel is None or is_error:
            return [(0.0, record)]
        tick = self.follower.on_frame(can_id, data) if channel == "io" else None
        if channel == "fieldbus" and can_id == 0 and data[:1] == b"\x01":
            self.started = True  # NMT START (command specifier 1)
        for armed in self.armed:
            spec = armed.spec
            if spec.target != channel or armed.hits >= spec.count:
                continue
            if spec.cob_id is not None and can_id != spec.cob_id:
                continue
            if channel == "io":
                if tick is None or not self._reached(spec, tick):
                    continue  # control frames are idempotent: not eligible
                u = _unit(spec.seed, self.follower.trial, tick, can_id)
            else:
                if can_id == 0 or not self._reached(spec, self.follower.tick):
                    continue
                nth = armed.seen.get(can_id, 0)
                armed.seen[can_id] = nth + 1
                u = _unit(spec.seed, can_id, nth)
            if u >= spec.rate:
                continue
            armed.hits += 1
            self.injected.append(
                write_record(
                    self.log_path,
                    {
                        "by": "hub",
                        "spec": spec.text,
                        "kind": spec.action,
                        "target": channel,
                        "trial": self.follower.trial,
                        "tick": tick if tick is not None else self.follower.tick,
                        "in_trial": self.follower.in_trial,
                        "kept": self.kept(),
                        "can_id": can_id,
                        "pid": os.getpid(),
                    },
                )
            )
            if spec.action == "drop":
                return []
            if spec.action == "duplicate":
                return [(0.0, record), (0.0, record)]
            if spec.action == "delay":
                return [(spec.delay_s, record)]
            return [(0.0, _error_record(record, overflow=spec.action == "overflow"))]
        return [(0.0, record)]


def _error_record(record: bytes, *, overflow: bool = False) -> bytes:
    """The hub record of the bus error frame the receivers get instead of ``record`` (the original's
    stamp kept): a CRC error for a damaged frame, a receive overflow (``overflow``) for one lost in
    their full queues."""
    import can

    from bus.can_errors import overflow_error_frame
    from bus.transports.hub.records import encode_record
    from bus.transports.hub.wire import STAMP, STAMP_OFFSET

    err = (
        overflow_error_frame(0.0)
        if overflow
        else can.Message(
            is_error_frame=True,
            arbitration_id=_CAN_ERR_PROT,
            is_extended_id=False,
            data=bytes([0, 0, 0, _CAN_ERR_PROT_LOC_CRC_SEQ, 0, 0, 0, 0]),
        )
    )
    rec = bytearray(encode_record(err))
    STAMP.pack_into(rec, STAMP_OFFSET, STAMP.unpack_from(record, STAMP_OFFSET)[0])
    return bytes(rec)

"""Every injection accounted for: what each ``--inject`` spec of a run did, for ``summary.json``.

This module owns :func:`account_injections`, which the launcher (:class:`host.rig.run_outcome.RunOutcome`)
calls on every exit path that leaves a summary. It reads the injection records of the run
(``logs/injections-*.jsonl``: the hub's frame faults, the launcher's kills, stalls and EMCY
frames, the host's full disk) and the run's fault records and gives one entry per spec::

    {"spec": "duplicate:fieldbus@before", "effect": "tolerated", "what": "...", "hits": 1,
     "by": "hub", "can_id": 1568, "kept": 0, "position": "before_first_trial", "trial": 0, "tick": null}

(``by``, ``can_id``, ``kept`` and the place — ``position``, ``trial``, ``tick`` as in a fault record —
are the first hit's; none of them when nothing was injected.)

``effect`` is one of

* ``fault`` — the run's fault came from it (a fault record's ``injected`` names it, and a kill,
  stall or EMCY names its target: a fault of another node that came after it is not its);
* ``tolerated`` — it was injected (``hits`` ≥ 1) and the protocol absorbed it: no fault followed
  from it (a duplicated or delayed SDO request answered correctly, a late or lost heartbeat
  inside its consumer time, a stall shorter than the consumer time); ``what`` says what was hit;
* ``not_injected`` — its moment never came or nothing was there to act on (the run ended before
  it, no eligible frame passed); ``what`` says which.

Nothing is silent: on a run that ends with exit 0 the launcher also prints one ``ilcrig: note:``
line per injection that was tolerated or not injected (:func:`note_lines`).

May import: ``bus``, :mod:`host.experiment` (faults).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from bus.cia301.emcy import EMCY_BASE
from bus.cia301.nmt import CONSUMER_TIME_MS, HEARTBEAT_BASE, NMT_COB_ID
from bus.io_frames import CONTROL_COB_ID, ENCODER_COB_BASE, N_JOINTS, TORQUE_COB_BASE
from bus.transports.fault_inject import FRAME_ACTIONS, FaultSpec
from bus.units import timeout_scale
from host.experiment.faults import Position, node_name, position_of

__all__ = ["FAULT", "NOT_INJECTED", "TOLERATED", "account_injections", "describe_frame", "note_lines"]

FAULT, TOLERATED, NOT_INJECTED = "fault", "tolerated", "not_injected"

#: CiA 301 SDO COB-ID bases (server → client answers, client → server requests)
_SDO_ANSWER_BASE, _SDO_REQUEST_BASE = 0x580, 0x600
_SYNC_COB_ID = 0x080


def describe_frame(channel: str, can_id: int) -> str:
    """What a frame of COB-ID ``can_id`` on ``channel`` (``io`` / ``fieldbus``) is, in words."""
    if channel == "io":
        if ENCODER_COB_BASE <= can_id < ENCODER_COB_BASE + N_JOINTS:
            return f"the encoder frame of joint {can_id - ENCODER_COB_BASE + 1} (0x{can_id:03X})"
        if TORQUE_COB_BASE <= can_id < TORQUE_COB_BASE + N_JOINTS:
            return f"the torque frame of joint {can_id - TORQUE_COB_BASE + 1} (0x{can_id:03X})"
        if can_id == CONTROL_COB_ID:
            return f"a trial control frame (0x{can_id:03X})"
        return f"io frame 0x{can_id:03X}"
    node = can_id & 0x7F
    if can_id == NMT_COB_ID:
        return "an NMT command (0x000)"
    if can_id == _SYNC_COB_ID:
        return "a SYNC (0x080)"
    if EMCY_BASE < can_id <= EMCY_BASE + 0x7F:
        return f"an EMCY of {node_name(node)} (0x{can_id:03X})"
    if _SDO_ANSWER_BASE < can_id <= _SDO_ANSWER_BASE + 0x7F:
        return f"an SDO answer of {node_name(node)} (0x{can_id:03X})"
    if _SDO_REQUEST_BASE < can_id <= _SDO_REQUEST_BASE + 0x7F:
        return f"an SDO request to {node_name(node)} (0x{can_id:03X})"
    if HEARTBEAT_BASE < can_id <= HEARTBEAT_BASE + 0x7F:
        return f"the heartbeat of {node_name(node)} (0x{can_id:03X})"
    return f"the PDO 0x{can_id:03X}"


def _absorbed(action: str, channel: str, can_id: int | None) -> str:
    """Why a hit frame left no fault: what the protocol does with it."""
    consumer_ms = CONSUMER_TIME_MS * timeout_scale()
    if channel == "fieldbus" and can_id is not None and HEARTBEAT_BASE < can_id <= HEARTBEAT_BASE + 0x7F:
        if action == "duplicate":
            return "a heartbeat twice only restarts its consumer time"
        return f"the node's next heartbeat came within its consumer time ({consumer_ms:.0f} ms)"
    if channel == "fieldbus" and can_id is not None and _SDO_ANSWER_BASE < can_id <= _SDO_REQUEST_BASE + 0x7F:
        if action == "duplicate":
            return "the SDO transfer completed correctly (the repeated frame was answered or ignored by the protocol)"
        if action == "delay":
            return "the SDO transfer completed correctly within its timeout"
        return "the SDO transfer completed correctly (the request was repeated)"
    if channel == "io":
        return "the lockstep took it (a frame within the tick deadline)"
    return "no node or the host took it for a fault"


def _what_tolerated(spec: FaultSpec, recs: list[dict[str, Any]]) -> str:
    first = recs[0]
    if spec.action in FRAME_ACTIONS:
        channel = str(first.get("target", spec.target))
        can_id = first.get("can_id")
        frame = describe_frame(channel, int(can_id)) if isinstance(can_id, int) else "a frame"
        verb = {"drop": "dropped", "corrupt": "damaged", "overflow": "lost", "duplicate": "duplicated", "delay": "delayed"}
        more = f" and {len(recs) - 1} more frame{'s' if len(recs) > 2 else ''}" if len(recs) > 1 else ""
        late = f" by {spec.delay_s * 1000:.0f} ms" if spec.action == "delay" else ""
        full = " in every receiver's full queue (receive overflow)" if spec.action == "overflow" else ""
        place = f"trial {first.get('trial')}, tick {first.get('tick')}" if first.get("in_trial") else "outside a trial"
        what = f"{verb[spec.action]} {frame}{more}{late}{full}"
        return f"{what} ({place}): {_absorbed(spec.action, channel, can_id)}; no fault followed"
    if spec.action == "stall":
        consumer_ms = CONSUMER_TIME_MS * timeout_scale()
        return (
            f"{spec.target} stopped for {spec.stall_s * 1000:.0f} ms: no heartbeat consumer took it for lost "
            f"(consumer time {consumer_ms:.0f} ms); no fault followed"
        )
    return f"{spec.action} of {spec.target or 'the run folder'} injected; no fault followed"


def account_injections(
    specs: Sequence[FaultSpec],
    records: Sequence[dict[str, Any]],
    faults: Sequence[dict[str, Any]],
    *,
    planned: int,
    ended_early: bool,
) -> list[dict[str, Any]]:
    """One entry per spec (module docstring). ``records``: the run's injection records (oldest
    first); ``faults``: the summary's fault records; ``planned``: the run's trials; ``ended_early``:
    the run ended before its end (a fault, an interrupt, a launch that failed)."""
    entries: list[dict[str, Any]] = []
    by_spec = {str((f.get("injected") or {}).get("spec")): f for f in reversed(faults) if f.get("injected")}
    unattributed = [f for f in faults if not f.get("injected")]
    seen: set[str] = set()
    for spec in specs:
        if spec.text in seen:
            continue
        seen.add(spec.text)
        recs = [r for r in records if r.get("spec") == spec.text]
        entry: dict[str, Any] = {"spec": spec.text, "hits": len(recs)}
        if recs:
            first = recs[0]
            entry |= {k: first.get(k) for k in ("by", "can_id", "kept") if k in first}
            entry |= _placed(first, planned)
        fault = by_spec.get(spec.text)
        if fault is None and recs and unattributed and _before(recs[0], unattributed[0]):
            fault = unattributed[0]
        if fault is not None and recs and _its_node(spec, fault):
            entry |= {"effect": FAULT, "what": f"{fault.get('kind')} of {fault.get('node')}: {fault.get('message')}"}
        elif recs:
            other = f"; the run's fault ({fault.get('kind')} of {fault.get('node')}) was not its" if fault is not None else ""
            entry |= {"effect": TOLERATED, "what": _what_tolerated(spec, recs) + other}
        elif ended_early:
            entry |= {"effect": NOT_INJECTED, "what": "the run had ended (or faulted) before its moment came"}
        else:
            entry |= {"effect": NOT_INJECTED, "what": _nothing_to_act_on(spec)}
        entries.append(entry)
    return entries


def _placed(rec: dict[str, Any], planned: int) -> dict[str, Any]:
    """Where in the run an injection record was made: position, trial, tick (as fault records)."""
    kept = rec.get("kept")
    in_trial = bool(rec.get("in_trial", rec.get("when") == "tick"))
    if not isinstance(kept, int):
        return {"trial": rec.get("trial"), "tick": rec.get("tick")}
    position, trial = position_of(kept, planned, in_trial and kept < planned)
    tick = rec.get("tick") if position == Position.IN_TRIAL else None
    return {"position": str(position), "trial": trial, "tick": tick}


def _its_node(spec: FaultSpec, fault: dict[str, Any]) -> bool:
    """A fault record can be of this injection: one of a process or a node (kill, stall, EMCY) names
    that process or node (the hub's: the hub); frame faults and a full disk can reach any node."""
    if spec.action in ("kill", "stall", "emcy"):
        return fault.get("node") == spec.target
    return True


def _before(rec: dict[str, Any], fault: dict[str, Any]) -> bool:
    """The injection record came before the fault was detected (same machine, both clocks)."""
    for inj_key, fault_key in (("t_mono", "t_detected_mono"), ("t_wall", "t_detected_wall")):
        if rec.get(inj_key) is not None and fault.get(fault_key) is not None:
            return float(rec[inj_key]) <= float(fault[fault_key]) + 1e-3
    return False


def _nothing_to_act_on(spec: FaultSpec) -> str:
    if spec.action in FRAME_ACTIONS:
        which = f"COB-ID 0x{spec.cob_id:03X}" if spec.cob_id is not None else "eligible"
        return f"no {which} frame passed on the {spec.target} after its moment (the run went on without it)"
    return f"{spec.target or 'its target'} was not there to act on at its moment"


def note_lines(entries: Sequence[dict[str, Any]], summary_path: str) -> list[str]:
    """The ``ilcrig: note:`` lines of a run that ended with exit 0: one per injection that was
    tolerated or not injected."""
    return [
        f"ilcrig: note: --inject {e['spec']} {'tolerated' if e['effect'] == TOLERATED else 'not injected'}: "
        f"{e['what']}; recorded in {summary_path}"
        for e in entries
        if e.get("effect") in (TOLERATED, NOT_INJECTED)
    ]

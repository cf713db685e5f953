"""``--inject`` specs and the hub's frame faults (bus/transports/fault_inject.py): the grammar, and
that which frames are hit depends only on the seed, trial, tick and COB-ID — the same seed, the
same faults, whatever the order the hub sees the frames in."""

from __future__ import annotations

import json
import random
from pathlib import Path

import can
import pytest

from bus import io_frames
from bus.can_errors import is_receive_overflow
from bus.errors import InputError
from bus.transports.fault_inject import FRAME_ACTIONS, FaultSpecError, FrameFaultInjector, parse_spec
from bus.transports.hub.records import decode_records, encode_record
from bus.transports.hub.wire import FLAG_ERR


def test_parse_the_forms() -> None:
    s = parse_spec("kill:drive2@1:150")
    assert (s.action, s.target, s.trial, s.tick) == ("kill", "drive2", 1, 150)
    s = parse_spec("stall:host@0:7,for=3.5")
    assert s.stall_s == 3.5
    s = parse_spec("drop:io@2:10,rate=0.25,seed=7,count=3,id=0x183")
    assert (s.rate, s.seed, s.count, s.cob_id) == (0.25, 7, 3, 0x183)
    assert parse_spec("delay:io@1:1").delay_s >= 2 * io_frames.TICK_TIMEOUT_S  # late by default
    assert parse_spec("delay:io@1:1,ms=20").delay_s == 0.02
    assert parse_spec("emcy:plant@1:2,code=0x8100").emcy_code == 0x8100
    s = parse_spec("diskfull@3")
    assert (s.action, s.trial) == ("diskfull", 3)


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("kill:drive5@1:1", "kill needs a role"),
        ("drop:can0@1:1", "drop needs a channel"),
        ("explode:io@1:1", "unknown action"),
        ("drop:io@-1:1", "trial and tick must be >= 0"),
        ("drop:io@1:1,rate=0", "rate must be in (0, 1]"),
        ("drop:io@1:1,count=0", "count must be an integer >= 1"),
        ("drop:io@1:1,for=2", "not known for drop"),
        ("drop:io@1:1,rate=nan", "must be finite"),
        ("emcy:drive1@1:1,code=0", "code must be an EMCY error code"),
        ("diskfull:x@1", "diskfull takes no target"),
        ("kill:drive2", "@WHEN is missing"),
        ("diskfull", "@WHEN is missing"),
    ],
)
def test_bad_specs_name_themselves(text: str, fragment: str) -> None:
    with pytest.raises(FaultSpecError) as exc:
        parse_spec(text)
    assert str(exc.value).startswith(f"--inject {text}") and fragment in str(exc.value)
    assert isinstance(exc.value, InputError)  # the one input-error type: exit code 2


def frames_of_trials(trials: int, ticks: int, shuffle: random.Random | None = None) -> list[can.Message]:
    """The io frames of ``trials`` trials: TRIAL_START, per tick 4 encoder + 4 torque frames
    (torque frames in a shuffled order, as they race to the hub), TRIAL_STOP."""
    out: list[can.Message] = []
    wire = 0
    for _ in range(trials):
        out.append(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_START, wire, ticks))
        for n in range(ticks):
            out += [io_frames.encode_encoder(j, wire + n, 1000 * j + n) for j in range(4)]
            torque = [io_frames.encode_torque(j, wire + n, 5 * n, io_frames.TorqueStatus.ENABLED) for j in range(4)]
            if shuffle is not None:
                shuffle.shuffle(torque)
            out += torque
        out.append(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_STOP, wire + ticks, ticks))
        wire += ticks + 1
    return out


def decode_one(record: bytes) -> can.Message:
    """The frame of one hub record."""
    msgs: list[can.Message] = []
    decode_records(record, "io", msgs.append)
    assert len(msgs) == 1
    return msgs[0]


def feed(inj: FrameFaultInjector, frames: list[can.Message]) -> list[tuple[float, bytes, int]]:
    """What the hub would deliver: (delay, record, can_id) per delivery."""
    delivered = []
    for msg in frames:
        rec = encode_record(msg)
        for delay, r in inj.deliveries("io", rec, msg.arbitration_id, bytes(msg.data)):
            delivered.append((delay, r, msg.arbitration_id))
    return delivered


def hits(inj: FrameFaultInjector) -> list[tuple[int, int, int]]:
    return sorted((r["trial"], r["tick"], r["can_id"]) for r in inj.injected)


@pytest.mark.parametrize("action", FRAME_ACTIONS)
def test_the_same_seed_hits_the_same_frames_whatever_their_order(action: str) -> None:
    spec = parse_spec(f"{action}:io@1:5,rate=0.05,seed=11,count=100")
    a = FrameFaultInjector([spec])
    b = FrameFaultInjector([spec])
    feed(a, frames_of_trials(3, 40, random.Random(1)))
    feed(b, frames_of_trials(3, 40, random.Random(2)))  # another race of the torque frames
    assert hits(a) == hits(b) and len(hits(a)) > 3
    assert all((t, n) >= (1, 5) for t, n, _ in hits(a))  # nothing before trial 1, tick 5
    assert all(cob != io_frames.CONTROL_COB_ID for _, _, cob in hits(a))  # control frames are not eligible
    c = FrameFaultInjector([parse_spec(f"{action}:io@1:5,rate=0.05,seed=12,count=100")])
    feed(c, frames_of_trials(3, 40, random.Random(1)))
    assert hits(c) != hits(a)  # another seed, other frames


def test_what_is_delivered(tmp_path: Path) -> None:
    frames = frames_of_trials(2, 10)
    log = tmp_path / "inj.jsonl"
    n = len(frames)
    out = feed(FrameFaultInjector([parse_spec("drop:io@1:3")], log), frames)
    assert len(out) == n - 1
    dropped = json.loads(log.read_text())
    assert (dropped["trial"], dropped["tick"], dropped["can_id"]) == (1, 3, io_frames.ENCODER_COB_BASE)
    assert {"t_mono", "t_wall", "spec"} <= set(dropped)
    out = feed(FrameFaultInjector([parse_spec("duplicate:io@0:0,id=0x182")]), frames)
    assert len(out) == n + 1
    out = feed(FrameFaultInjector([parse_spec("corrupt:io@0:4")]), frames)
    errors = [r for _, r, _ in out if r[1] & FLAG_ERR]
    assert len(out) == n and len(errors) == 1  # the damaged frame became a bus error frame
    assert not is_receive_overflow(decode_one(errors[0]))  # a CRC error, frames damaged
    out = feed(FrameFaultInjector([parse_spec("overflow:io@0:4")]), frames)
    errors = [r for _, r, _ in out if r[1] & FLAG_ERR]
    assert len(out) == n and len(errors) == 1  # the frame lost in the receivers' queues: their overflow error frame
    assert is_receive_overflow(decode_one(errors[0]))
    out = feed(FrameFaultInjector([parse_spec("delay:io@0:4,ms=30")]), frames)
    assert [d for d, _, _ in out if d > 0] == [0.03]
    out = feed(FrameFaultInjector([parse_spec("drop:io@1:3")]), frames)  # a fresh injector: count 1
    assert len(out) == n - 1


def test_a_frame_fault_after_a_trial_acts_when_the_summary_holds_it(tmp_path: Path) -> None:
    """``@T:end`` / ``@after``: not when the plant ends trial T, but when the summary holds it (the
    moment docs/faults.md gives, the same as the launcher's injections)."""
    summary = tmp_path / "summary.json"
    sdo = can.Message(arbitration_id=0x602, is_extended_id=False, data=bytes(8))
    for text in ("drop:fieldbus@0:end", "drop:fieldbus@after"):
        inj = FrameFaultInjector([parse_spec(text)], iterations=1, summary=summary)
        inj.kept.poll_s = 0.0
        feed(inj, frames_of_trials(1, 5))  # trial 0 ended on the io channel
        summary.write_text(json.dumps({"iterations": []}))
        assert inj.deliveries("fieldbus", encode_record(sdo), 0x602, bytes(8)) != []  # not yet: the summary holds no trial
        summary.write_text(json.dumps({"iterations": [{"iteration": 0}]}))
        assert inj.deliveries("fieldbus", encode_record(sdo), 0x602, bytes(8)) == []  # now: dropped
        assert inj.injected[0]["kept"] == 1 and inj.injected[0]["in_trial"] is False
        summary.unlink()

"""bus.canlog: candump logs written with python-can's writer and read back frame by frame."""

from __future__ import annotations

import random
from pathlib import Path
from typing import IO

import can
import pytest
from cli_util import stop_process

from bus.bus_features import frames_from_messages
from bus.canlog import CanLogError, open_log, read_log
from bus.io_frames import TorqueStatus, encode_encoder, encode_torque


def _frames() -> list[can.Message]:
    out = []
    t = 1_700_000_000.0
    for n in range(3):
        for j in range(4):
            m = encode_encoder(j, n, 1000 * j - n)
            m.timestamp = t + n * 1e-3
            out.append(m)
            m = encode_torque(j, n, -50_000 * j, TorqueStatus.ENABLED)
            m.timestamp = t + n * 1e-3 + 1e-4
            out.append(m)
    out.append(can.Message(timestamp=t + 1, arbitration_id=0x1ABCDEF0, is_extended_id=True, data=b"\x01\x02"))
    out.append(can.Message(timestamp=t + 2, arbitration_id=0x701, is_extended_id=False, is_remote_frame=True, dlc=1))
    out.append(can.Message(timestamp=t + 3, arbitration_id=0x080, is_extended_id=False, data=b""))
    return out


def test_log_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "io.log"
    sent = _frames()
    with open_log(path, "io") as log:
        for m in sent:
            log(m)
    assert log.frames == len(sent)
    text = path.read_text().splitlines()
    assert text[0] == "(1700000000.000000) io 101#000000000000 R"
    assert text[1] == "(1700000000.000100) io 181#000000000000" + "01 R"
    assert text[-2] == "(1700000002.000000) io 701#R R"
    back = list(read_log(path))
    assert len(back) == len(sent)
    for a, b in zip(sent, back, strict=True):
        assert b.arbitration_id == a.arbitration_id
        assert b.is_extended_id == a.is_extended_id
        assert b.is_remote_frame == a.is_remote_frame
        assert b.dlc == (0 if a.is_remote_frame else a.dlc)  # the writer drops an RTR's DLC
        assert b.is_rx
        assert bytes(b.data) == bytes(a.data)
        assert b.channel == "io"
        assert b.timestamp == pytest.approx(a.timestamp, abs=1e-6)


def test_log_sent_and_channel_override(tmp_path: Path) -> None:
    path = tmp_path / "fieldbus.log"
    with open_log(path, "fieldbus") as log:
        m = can.Message(arbitration_id=0x601, is_extended_id=False, data=b"\x40\x41\x60\x00", channel="unix:/x#fieldbus")
        log.log_sent(m, timestamp=12.5)
        m.timestamp = 13.0
        log(m)
    lines = path.read_text().splitlines()
    assert lines == ["(12.500000) fieldbus 601#40416000 T", "(13.000000) fieldbus 601#40416000 R"]
    assert [m.is_rx for m in read_log(path)] == [False, True]
    assert m.channel == "unix:/x#fieldbus"  # the caller's message is not modified


def test_logreader_via_can_logger_style_name(tmp_path: Path) -> None:
    """can.Logger picks the candump writer for a .log name too, so both agree."""
    path = tmp_path / "x.log"
    with can.Logger(path) as lg:
        lg(can.Message(timestamp=1.0, arbitration_id=0x123, is_extended_id=False, data=b"\xaa", channel="io"))
    assert [bytes(m.data) for m in read_log(path)] == [b"\xaa"]


@pytest.mark.parametrize("name,channel", [("x.asc", "io"), ("x.log", "two words"), ("x.log", "")])
def test_bad_arguments(tmp_path: Path, name: str, channel: str) -> None:
    with pytest.raises(CanLogError):
        open_log(tmp_path / name, channel)


def test_stop_is_idempotent(tmp_path: Path) -> None:
    log = open_log(tmp_path / "a.log", "io")
    log.stop()
    log.stop()


def _readline(stream: IO[str], timeout_s: float) -> str:
    """One line from a child's stdout pipe, or "" if none came within ``timeout_s``."""
    import select

    if not select.select([stream], [], [], timeout_s)[0]:
        return ""
    return stream.readline()


@pytest.mark.multiprocess
def test_python_can_logger_records_a_hub_channel(tmp_path: Path) -> None:
    """python-can's own `can.logger` joins the hub through the entry point and writes candump.

    Events, no sleeps: the logger prints "Connected to ..." once its bus is up (the hub has
    registered it: frames flow to it from then on).  The end of the recording is the end of
    the hub's stream: when the hub stops, the logger reads every frame queued before the
    end-of-stream, its loop ends and it writes the file on the way out.  (A SIGINT instead would
    drop whatever the logger had not read yet.)"""
    import os
    import signal
    import subprocess
    import sys

    from bus.transports.hub.client import HubBus
    from bus.transports.hub.process import start_hub

    path = tmp_path / "io.log"
    with start_hub() as hub:
        channel = hub.channel("io")
        proc = subprocess.Popen(
            [sys.executable, "-m", "can.logger", "-i", "ilcrig_hub", "-c", channel, "-f", str(path)],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        assert proc.stdout is not None
        try:
            line = _readline(proc.stdout, 30.0)
            assert line.startswith("Connected to HubBus"), line
            sent = [encode_encoder(j, 9, 100 * j) for j in range(4)]
            with HubBus(hub.channel("io")) as bus, HubBus(hub.channel("io")) as witness:
                for m in sent:
                    bus.send(m)
                assert all(witness.recv(5.0) is not None for _ in sent)  # the hub routed them all
            hub.stop()  # end of the stream, behind the frames
            proc.wait(10)  # the logger saw the end: everything before it is read and written
        finally:
            if proc.poll() is None:
                stop_process(proc, signal.SIGINT)
            proc.stdout.close()
    back = list(read_log(path))
    # can.logger writes msg.channel as it is: the full hub channel string (bus.transports.hub.client)
    assert [(m.arbitration_id, bytes(m.data), m.channel) for m in back] == [
        (m.arbitration_id, bytes(m.data), channel) for m in sent
    ]


def test_frames_written_as_arrays_give_the_same_lines(tmp_path: Path) -> None:
    rng = random.Random(7)
    msgs = _frames()
    t = 1_795_403_351.3251324
    for i in range(500):  # classic frames of every length, received and sent, some out of order
        t += rng.random() * 1e-4
        msgs.append(
            can.Message(
                timestamp=t - (10 if i == 3 else 0),
                arbitration_id=rng.choice([0, 0x10, 0x101, 0x7FF]),
                is_extended_id=False,
                is_rx=rng.random() < 0.8,
                data=bytes(rng.randrange(256) for _ in range(rng.randrange(9))),
            )
        )
    msgs.append(can.Message(timestamp=t + 1, arbitration_id=0x1, is_extended_id=False, data=b"\x01"))
    one, many = tmp_path / "one.log", tmp_path / "many.log"
    with open_log(one, "io") as log:
        for m in msgs:
            log(m)
    frames = frames_from_messages(msgs)
    with open_log(many, "io") as log:
        log.write_frames(frames[:50])  # with the extended and remote frames: one by one
        log.write_frames(frames[50:300])  # classic frames only: with numpy
        log.write_frames(frames[300:])
        log.write_frames(frames[:0])
    assert log.frames == len(msgs)
    assert many.read_text() == one.read_text()

"""Tests of bus/cia301/nmt.py (NMT command and heartbeat codecs, heartbeat consumer) and bus/cia301/emcy.py."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bus.cia301.emcy import (
    EmcyCode,
    EmcyFrameError,
    EmcyMessage,
    ErrorRegister,
    decode_emcy,
    emcy_cob_id,
    emcy_node_id,
    encode_emcy,
)
from bus.cia301.nmt import (
    HeartbeatConsumer,
    NmtCommand,
    NmtFrameError,
    NmtState,
    decode_heartbeat,
    decode_nmt,
    encode_heartbeat,
    encode_nmt,
    heartbeat_cob_id,
    heartbeat_node_id,
    next_state,
    nmt_addresses,
)

# --------------------------------------------------------------------------- NMT


@pytest.mark.parametrize(
    ("command", "node", "data"),
    [
        (NmtCommand.START, 3, b"\x01\x03"),
        (NmtCommand.STOP, 0, b"\x02\x00"),
        (NmtCommand.ENTER_PRE_OPERATIONAL, 127, b"\x80\x7f"),
        (NmtCommand.RESET_NODE, 1, b"\x81\x01"),
        (NmtCommand.RESET_COMMUNICATION, 0, b"\x82\x00"),
    ],
)
def test_nmt_command_bytes(command: NmtCommand, node: int, data: bytes) -> None:
    assert encode_nmt(command, node) == data
    assert decode_nmt(data) == (command, node)


def test_nmt_matches_canopen_library_bytes() -> None:
    from canopen.nmt import COMMAND_TO_STATE, NMT_COMMANDS

    assert NMT_COMMANDS["OPERATIONAL"] == NmtCommand.START
    assert NMT_COMMANDS["STOPPED"] == NmtCommand.STOP
    assert NMT_COMMANDS["PRE-OPERATIONAL"] == NmtCommand.ENTER_PRE_OPERATIONAL
    assert NMT_COMMANDS["RESET"] == NmtCommand.RESET_NODE
    assert NMT_COMMANDS["RESET COMMUNICATION"] == NmtCommand.RESET_COMMUNICATION
    assert set(COMMAND_TO_STATE) >= {int(c) for c in NmtCommand}


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"\x01", "2 data bytes"),
        (b"\x01\x02\x03", "2 data bytes"),
        (b"\x03\x01", "unknown NMT command"),
        (b"\x01\x80", "node id"),
    ],
)
def test_nmt_decode_rejects(data: bytes, match: str) -> None:
    with pytest.raises(NmtFrameError, match=match):
        decode_nmt(data)
    assert issubclass(NmtFrameError, ValueError)


def test_nmt_encode_rejects() -> None:
    with pytest.raises(NmtFrameError, match="unknown"):
        encode_nmt(0x05, 1)
    with pytest.raises(NmtFrameError, match="node id"):
        encode_nmt(NmtCommand.START, 128)


def test_nmt_addresses() -> None:
    assert nmt_addresses(b"\x01\x00", 4) is NmtCommand.START
    assert nmt_addresses(b"\x01\x04", 4) is NmtCommand.START
    assert nmt_addresses(b"\x01\x05", 4) is None


def test_next_state() -> None:
    s = NmtState.PRE_OPERATIONAL
    assert next_state(s, NmtCommand.START) is NmtState.OPERATIONAL
    assert next_state(NmtState.OPERATIONAL, NmtCommand.STOP) is NmtState.STOPPED
    assert next_state(NmtState.STOPPED, NmtCommand.ENTER_PRE_OPERATIONAL) is s
    assert next_state(NmtState.OPERATIONAL, NmtCommand.RESET_NODE) is s
    assert next_state(NmtState.STOPPED, NmtCommand.RESET_COMMUNICATION) is s


@given(command=st.sampled_from(list(NmtCommand)), node=st.integers(0, 127))
def test_nmt_round_trip(command: NmtCommand, node: int) -> None:
    assert decode_nmt(encode_nmt(command, node)) == (command, node)


# --------------------------------------------------------------------------- heartbeat


def test_heartbeat_bytes_and_cob_id() -> None:
    assert encode_heartbeat(NmtState.BOOT_UP) == b"\x00"
    assert encode_heartbeat(NmtState.STOPPED) == b"\x04"
    assert encode_heartbeat(NmtState.OPERATIONAL) == b"\x05"
    assert encode_heartbeat(NmtState.PRE_OPERATIONAL) == b"\x7f"
    assert heartbeat_cob_id(1) == 0x701 and heartbeat_cob_id(127) == 0x77F
    assert heartbeat_node_id(0x705) == 5
    assert heartbeat_node_id(0x700) is None and heartbeat_node_id(0x605) is None
    with pytest.raises(NmtFrameError):
        heartbeat_cob_id(0)


def test_heartbeat_decode_ignores_toggle_bit_and_rejects_bad() -> None:
    assert decode_heartbeat(b"\x85") is NmtState.OPERATIONAL
    assert decode_heartbeat(b"\xff") is NmtState.PRE_OPERATIONAL
    with pytest.raises(NmtFrameError, match="1 data byte"):
        decode_heartbeat(b"")
    with pytest.raises(NmtFrameError, match="not a heartbeat state"):
        decode_heartbeat(b"\x06")
    with pytest.raises(NmtFrameError):
        encode_heartbeat(0x06)


@given(state=st.sampled_from(list(NmtState)), toggle=st.booleans())
def test_heartbeat_round_trip(state: NmtState, toggle: bool) -> None:
    data = encode_heartbeat(state)
    assert decode_heartbeat(bytes([data[0] | (0x80 if toggle else 0)])) is state


def test_heartbeat_consumer_overdue_and_booted() -> None:
    hb = HeartbeatConsumer({1: 0.15, 2: 0.15})
    assert hb.report_at(10.0).overdue == []  # monitoring starts at 10.0
    hb.on_heartbeat(1, b"\x00", 10.01)  # boot-up
    hb.on_heartbeat(1, b"\x7f", 10.1)
    report = hb.report_at(10.12)
    assert report.booted == [1] and report.overdue == []
    assert report.states == {1: NmtState.PRE_OPERATIONAL}
    report = hb.report_at(10.2)
    assert report.booted == []  # boot-ups are reported once
    assert report.overdue == [2]  # never heard, 0.2 s > 0.15 s since monitoring started
    report = hb.report_at(10.3)
    assert report.overdue == [1, 2]
    assert hb.on_frame(0x702, b"\x05", 10.31) is NmtState.OPERATIONAL
    assert hb.on_frame(0x185, b"\x05", 10.31) is None
    assert hb.report_at(10.32).overdue == [1]
    assert hb.state(2) is NmtState.OPERATIONAL and hb.state(3) is None


def test_heartbeat_consumer_rejects_bad_setup() -> None:
    hb = HeartbeatConsumer()
    with pytest.raises(ValueError):
        hb.watch(1, 0.0)
    with pytest.raises(NmtFrameError):
        hb.watch(0, 1.0)
    with pytest.raises(NmtFrameError):
        hb.on_heartbeat(1, b"\x01", 0.0)


def test_heartbeat_consumer_unwatched_node_is_only_recorded() -> None:
    hb = HeartbeatConsumer()
    hb.on_heartbeat(9, b"\x00", 1.0)
    report = hb.report_at(100.0)
    assert report.booted == [9] and report.overdue == []


# --------------------------------------------------------------------------- EMCY


def test_emcy_bytes() -> None:
    register = ErrorRegister.GENERIC | ErrorRegister.DEVICE_PROFILE
    assert encode_emcy(EmcyCode.FOLLOWING_ERROR, register, b"\x01\x02") == bytes.fromhex("11 86 21 01 02 00 00 00")
    assert encode_emcy(EmcyCode.ERROR_RESET) == bytes(8)
    msg = decode_emcy(bytes.fromhex("10 23 03 aa bb cc dd ee"))
    assert msg == EmcyMessage(EmcyCode.OVER_CURRENT, 0x03, bytes.fromhex("aa bb cc dd ee"))
    assert not msg.is_reset and decode_emcy(bytes(8)).is_reset
    assert "0x2310 (OVER_CURRENT)" in str(msg)
    assert emcy_cob_id(4) == 0x084
    assert emcy_node_id(0x084) == 4 and emcy_node_id(0x080) is None


def test_emcy_code_values() -> None:
    assert EmcyCode.ERROR_RESET == 0x0000
    assert EmcyCode.OVER_CURRENT == 0x2310
    assert EmcyCode.DC_LINK_OVER_VOLTAGE == 0x3210
    assert EmcyCode.DRIVE_TEMPERATURE == 0x4310
    assert EmcyCode.FOLLOWING_ERROR == 0x8611


def test_emcy_matches_canopen_library_decoder() -> None:
    from canopen.emcy import EmcyConsumer

    consumer = EmcyConsumer()
    consumer.on_emcy(0x085, encode_emcy(0x8611, 0x21, b"\x05\x04\x03\x02\x01"), 1.0)
    err = consumer.active[0]
    assert err.code == 0x8611 and err.register == 0x21 and err.data == b"\x05\x04\x03\x02\x01"
    consumer.on_emcy(0x085, encode_emcy(EmcyCode.ERROR_RESET), 2.0)
    assert consumer.active == []


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"code": 0x10000}, "U16"),
        ({"code": -1}, "U16"),
        ({"code": 1, "register": 256}, "U8"),
        ({"code": 1, "manufacturer": bytes(6)}, "at most 5"),
    ],
)
def test_emcy_rejects(kwargs: dict, match: str) -> None:
    with pytest.raises(EmcyFrameError, match=match):
        EmcyMessage(**kwargs)
    with pytest.raises(EmcyFrameError, match="8 data bytes"):
        decode_emcy(bytes(7))
    with pytest.raises(EmcyFrameError):
        emcy_cob_id(128)


@given(code=st.integers(0, 0xFFFF), register=st.integers(0, 0xFF), manufacturer=st.binary(min_size=0, max_size=5))
def test_emcy_round_trip(code: int, register: int, manufacturer: bytes) -> None:
    data = encode_emcy(code, register, manufacturer)
    assert len(data) == 8
    msg = decode_emcy(data)
    assert (msg.code, msg.register) == (code, register)
    assert msg.manufacturer == manufacturer.ljust(5, b"\x00")
    assert msg.encode() == data

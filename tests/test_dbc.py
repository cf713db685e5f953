"""The DBC files of the rig's cyclic frames (bus/rig_io.dbc, bus/rig_fieldbus.dbc) against the
codecs that send the frames: the committed files are the generated text, and cantools decodes
every frame the codecs encode to the same integers."""

from __future__ import annotations

import cantools
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bus import io_frames
from bus.cyclic import decode_tpdo, encode_csp_rpdo, rpdo_cob_id, tpdo_cob_id
from bus.dbc import FIELDBUS_DBC_PATH, IO_DBC_PATH, fieldbus_dbc, io_dbc
from host.cli.dbc import main

I32 = st.integers(-(1 << 31), (1 << 31) - 1)
I16 = st.integers(-(1 << 15), (1 << 15) - 1)
TICK = st.integers(0, 0xFFFF)


@pytest.fixture(scope="module")
def io_db() -> cantools.database.Database:
    return cantools.database.load_file(str(IO_DBC_PATH))


@pytest.fixture(scope="module")
def fb_db() -> cantools.database.Database:
    return cantools.database.load_file(str(FIELDBUS_DBC_PATH))


def test_committed_files_are_the_generated_text() -> None:
    assert IO_DBC_PATH.read_text() == io_dbc()
    assert FIELDBUS_DBC_PATH.read_text() == fieldbus_dbc()
    assert main(["--check"]) == 0


def test_every_io_and_pdo_frame_is_described(io_db: cantools.database.Database, fb_db: cantools.database.Database) -> None:
    io_ids = {m.frame_id for m in io_db.messages}
    assert io_ids == (
        {io_frames.CONTROL_COB_ID}
        | {io_frames.encoder_cob_id(j) for j in range(4)}
        | {io_frames.torque_cob_id(j) for j in range(4)}
    )
    assert {m.frame_id for m in fb_db.messages} == (
        {0x080} | {rpdo_cob_id(n) for n in (1, 2, 3, 4)} | {tpdo_cob_id(n) for n in (1, 2, 3, 4)}
    )
    for m in io_db.messages:  # lengths as the codecs send them
        assert m.length == {0x010: 7}.get(m.frame_id, 6 if m.frame_id < 0x181 else 7)


@given(joint=st.integers(0, 3), tick=TICK, count=I32, torque=I32, status=st.integers(0, 15))
def test_cantools_decodes_io_frames_as_the_codecs_encode_them(
    io_db: cantools.database.Database, joint: int, tick: int, count: int, torque: int, status: int
) -> None:
    enc = io_frames.encode_encoder(joint, tick, count)
    assert io_db.decode_message(enc.arbitration_id, bytes(enc.data), scaling=False) == {"position": count, "wire_tick": tick}
    tq = io_frames.encode_torque(joint, tick, torque, status)
    got = io_db.decode_message(tq.arbitration_id, bytes(tq.data), scaling=False)
    assert got["torque"] == torque and got["wire_tick"] == tick
    assert [got[f"status_{n}"] for n in ("enabled", "fault", "saturated", "warning")] == [(status >> b) & 1 for b in range(4)]
    ctl = io_frames.encode_control(io_frames.IoControlCommand.TRIAL_START, tick, 501)
    assert io_db.decode_message(ctl.arbitration_id, bytes(ctl.data), scaling=False, decode_choices=False) == {
        "command": 1,
        "wire_tick": tick,
        "n_ticks": 501,
    }


@given(node=st.integers(1, 4), pos=I32, permille=I16)
def test_cantools_decodes_the_pdos_as_the_codecs_encode_them(
    fb_db: cantools.database.Database, node: int, pos: int, permille: int
) -> None:
    got = fb_db.decode_message(rpdo_cob_id(node), encode_csp_rpdo(pos, permille), scaling=False)
    assert got == {"target_position": pos, "torque_offset": permille}
    data = fb_db.encode_message(tpdo_cob_id(node), {"position_actual": pos, "torque_actual": permille}, scaling=False)
    assert decode_tpdo(data) == (pos, permille)
    phys = fb_db.decode_message(tpdo_cob_id(node), data)
    assert phys["torque_actual"] == pytest.approx(permille * 0.0882)

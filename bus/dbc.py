"""DBC descriptions of the rig's cyclic frames, generated from the codecs that send them.

This module owns ``bus/rig_io.dbc`` (the io channel: control, encoder and torque frames of
:mod:`bus.io_frames`) and ``bus/rig_fieldbus.dbc`` (the fieldbus's cyclic frames of the pdo
transport: SYNC, RPDO1 and TPDO1 of every drive as :mod:`bus.cyclic` maps them).  Two files
because the two channels reuse identifiers (0x181–0x184 is a torque frame on io and a TPDO on the
fieldbus), and a DBC describes one bus.  The files are text generated here (``python -m host.cli.dbc``
rewrites them); ``tests/test_dbc.py`` checks that the committed files equal the generated text and
that ``cantools`` decodes every frame the codecs encode to the same values, so a CAN engineer's
tools read ``io.log`` / ``fieldbus.log`` (candump format) of a run::

    python -m cantools decode bus/rig_io.dbc < runs/x/io.log
    python -m cantools plot bus/rig_io.dbc '*ENCODER*position*' < runs/x/io.log

Signals carry the wire integers with a scale to physical units: positions in counts (factor 1;
1 count = 2π/(10·2²⁰) rad at the joint), torques in N·m (io: µN·m × 1e-6; PDOs: ‰ of the rated
torque 0x6076 × 0.0882 N·m).
"""

from __future__ import annotations

import logging
from pathlib import Path

from bus import io_frames
from bus.cyclic import CSP_RPDO_MAP, SYNC_COB_ID, TPDO_MAP, map_bytes, rpdo_cob_id, tpdo_cob_id
from bus.objects import DRIVE_NODE_IDS, RATED_TORQUE_MNM

logger = logging.getLogger(__name__)

_HERE = Path(__file__).resolve().parent
IO_DBC_PATH: Path = _HERE / "rig_io.dbc"
FIELDBUS_DBC_PATH: Path = _HERE / "rig_fieldbus.dbc"

_HEADER = """VERSION ""


NS_ :
\tCM_
\tVAL_

BS_:

BU_: {nodes}

"""
_PERMILLE_NM = RATED_TORQUE_MNM / 1e6  # N·m per ‰ of the rated torque


def _signal(name: str, start: int, bits: int, signed: bool, factor: float, unit: str, receivers: str) -> str:
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    f = f"{factor:.10g}"
    return (
        f" SG_ {name} : {start}|{bits}@1{'-' if signed else '+'} ({f},0) "
        f'[{lo * factor:.10g}|{hi * factor:.10g}] "{unit}" {receivers}\n'
    )


def io_dbc() -> str:
    """The io channel's DBC text."""
    drives = ",".join(f"DRIVE{n}" for n in DRIVE_NODE_IDS)
    out = _HEADER.format(nodes="PLANT " + " ".join(f"DRIVE{n}" for n in DRIVE_NODE_IDS))
    comments = []
    cid = io_frames.CONTROL_COB_ID
    out += f"BO_ {cid} IO_CONTROL: 7 PLANT\n"
    out += _signal("command", 0, 8, False, 1, "", drives)
    out += _signal("wire_tick", 8, 16, False, 1, "tick", drives)
    out += _signal("n_ticks", 24, 32, False, 1, "ticks", drives)
    out += "\n"
    comments.append(f'CM_ BO_ {cid} "trial start/stop, plant to all drives";')
    for j in range(io_frames.N_JOINTS):
        e, t = io_frames.encoder_cob_id(j), io_frames.torque_cob_id(j)
        out += f"BO_ {e} IO_ENCODER_J{j + 1}: 6 PLANT\n"
        out += _signal("position", 0, 32, True, 1, "counts", f"DRIVE{j + 1}")
        out += _signal("wire_tick", 32, 16, False, 1, "tick", f"DRIVE{j + 1}")
        out += "\n"
        out += f"BO_ {t} IO_TORQUE_J{j + 1}: 7 DRIVE{j + 1}\n"
        out += _signal("torque", 0, 32, True, 1e-6, "N.m", "PLANT")
        out += _signal("wire_tick", 32, 16, False, 1, "tick", "PLANT")
        for bit, name in enumerate(("enabled", "fault", "saturated", "warning")):
            out += _signal(f"status_{name}", 48 + bit, 1, False, 1, "", "PLANT")
        out += "\n"
        comments.append(f'CM_ BO_ {e} "encoder count of joint {j + 1} (q(t_n)), plant to drive {j + 1}";')
        comments.append(f'CM_ BO_ {t} "torque command of joint {j + 1} for the same tick, drive {j + 1} to plant";')
    out += "\n".join(comments) + "\n"
    out += f'VAL_ {cid} command 1 "TRIAL_START" 2 "TRIAL_STOP" ;\n'
    return out


def fieldbus_dbc() -> str:
    """The fieldbus's cyclic frames (pdo transport) as a DBC text."""
    out = _HEADER.format(nodes="HOST " + " ".join(f"DRIVE{n}" for n in DRIVE_NODE_IDS))
    assert [b for _, _, b in CSP_RPDO_MAP] == [32, 16] and [b for _, _, b in TPDO_MAP] == [32, 16]
    out += f"BO_ {SYNC_COB_ID} SYNC: 0 HOST\n\n"
    comments = [f'CM_ BO_ {SYNC_COB_ID} "CANopen SYNC (no counter), one per control period";']
    for n in DRIVE_NODE_IDS:
        r, t = rpdo_cob_id(n), tpdo_cob_id(n)
        out += f"BO_ {r} RPDO1_NODE{n}: {map_bytes(CSP_RPDO_MAP)} HOST\n"
        out += _signal("target_position", 0, 32, True, 1, "counts", f"DRIVE{n}")
        out += _signal("torque_offset", 32, 16, True, _PERMILLE_NM, "N.m", f"DRIVE{n}")
        out += "\n"
        out += f"BO_ {t} TPDO1_NODE{n}: {map_bytes(TPDO_MAP)} DRIVE{n}\n"
        out += _signal("position_actual", 0, 32, True, 1, "counts", "HOST")
        out += _signal("torque_actual", 32, 16, True, _PERMILLE_NM, "N.m", "HOST")
        out += "\n"
        comments.append(f'CM_ BO_ {r} "drive {n} CSP set-points: 0x607A target position, 0x60B2 torque offset";')
        comments.append(f'CM_ BO_ {t} "drive {n} actuals: 0x6064 position, 0x6077 torque";')
    return out + "\n".join(comments) + "\n"


def write_dbc_files(io_path: Path = IO_DBC_PATH, fieldbus_path: Path = FIELDBUS_DBC_PATH) -> None:
    """(Re)write both DBC files."""
    io_path.write_text(io_dbc())
    fieldbus_path.write_text(fieldbus_dbc())
    logger.info("wrote %s and %s", io_path, fieldbus_path)


def stale_dbc_files() -> list[Path]:
    """The DBC files that are missing or differ from the generated text (each logged as an error)."""
    generated = ((IO_DBC_PATH, io_dbc()), (FIELDBUS_DBC_PATH, fieldbus_dbc()))
    stale = [p for p, text in generated if not p.exists() or p.read_text() != text]
    for p in stale:
        logger.error("%s is not the generated text: run python -m host.cli.dbc", p)
    return stale

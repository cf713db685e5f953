"""Object-dictionary indices, sub-indices and value encodings of the emulated drive.

Owns the names of every object the drive exposes (described in full, with data
types, access and limits, by ``bus/drive.eds``), the CiA 402 controlword /
statusword encodings both sides must agree on, the manufacturer trial/recorder
enumerations, EMCY codes, and the little-endian packing of int32 tables.

Layout of the manufacturer objects (maxon/Elmo pattern, docs/canopen-objects.md §5):

======  ===  ========================  =======  ==========================================
index   sub  name                      type     meaning / unit
======  ===  ========================  =======  ==========================================
0x2100  0    reference position table  DOMAIN   N × int32 LE counts (rw)
0x2101  0    reference velocity table  DOMAIN   N × int32 LE counts/s (rw)
0x2102  0    feed-forward torque table DOMAIN   N × int32 LE µN·m (rw)
0x2103  1    table length N            U32      samples; tables must be 4·N bytes
0x2103  2    table capacity            U32      const, max N
0x2103  3    tables loaded             U8       ro bit mask: 1 ref pos, 2 ref vel, 4 ff
0x2110  1    Kp                        I32      Q16 µN·m/count (bus.fixedpoint)
0x2110  2    Kd                        I32      Q16 µN·m/(count/s)
0x2110  3    velocity filter coeff.    U16      Q15, 1..32768 (32768 = unfiltered)
0x2110  4    control structure         U8       0 PD, 1 cascade (0x60FB, 0x60F9)
0x2120  1    trial command             U8       wo: 1 = arm, 0 = disarm/abort
0x2120  2    trial state               U8       ro: :class:`TrialState`
0x2120  3    trial tick count          U32      ro: ticks played in this trial
0x2120  4    last fault cause          U8       ro: :class:`FaultCause`
0x2200  1    recorder status           U8       ro: :class:`RecorderStatus`
0x2200  2    recorded samples          U32      ro
0x2200  3    channels                  U8       const 4
0x2200  4    recorder capacity         U32      const, samples per channel
0x2210  0    recorder data             DOMAIN   ro: 4 int32 planes back to back (see below)
0x2300  0    control period            U32      µs
======  ===  ========================  =======  ==========================================

Recorder planes, each ``recorded samples`` int32 LE long, in this order: position
(counts), velocity estimate (counts/s), total torque (µN·m, as applied), feedback torque
(µN·m, before the clamp).
"""

from __future__ import annotations

import logging
import struct
from enum import IntEnum, IntFlag
from pathlib import Path
from typing import Final

import numpy as np
import numpy.typing as npt

logger = logging.getLogger(__name__)


class Obj(IntEnum):
    """Object indices."""

    # CiA 301
    DEVICE_TYPE = 0x1000
    ERROR_REGISTER = 0x1001
    ERROR_HISTORY = 0x1003  # sub 0: number of errors (write 0: clear), subs 1..8: newest first
    DEVICE_NAME = 0x1008
    SOFTWARE_VERSION = 0x100A
    COB_ID_SYNC = 0x1005
    COMM_CYCLE_PERIOD = 0x1006  # U32 µs: the SYNC period expected (0 = no SYNC watchdog)
    STORE_PARAMETERS = 0x1010  # write "save" to sub 1..3
    RESTORE_DEFAULTS = 0x1011  # write "load" to sub 1..3
    COB_ID_EMCY = 0x1014
    INHIBIT_TIME_EMCY = 0x1015
    CONSUMER_HEARTBEAT = 0x1016
    PRODUCER_HEARTBEAT = 0x1017
    IDENTITY = 0x1018
    SYNC_COUNTER_OVERFLOW = 0x1019  # U8: 0 = SYNC without counter, 2..240
    SDO_SERVER = 0x1200
    ERROR_BEHAVIOUR = 0x1029  # sub 1: NMT reaction to a communication error
    # CiA 402
    ABORT_CONNECTION_OPTION = 0x6007  # I16 (AbortConnectionOption)
    ERROR_CODE = 0x603F
    CONTROLWORD = 0x6040
    STATUSWORD = 0x6041
    QUICK_STOP_OPTION = 0x605A  # I16 (QuickStopOption)
    MODES_OF_OPERATION = 0x6060
    MODES_OF_OPERATION_DISPLAY = 0x6061
    POSITION_DEMAND = 0x6062  # I32 counts: the position set-point of the last control cycle
    POSITION_ACTUAL = 0x6064
    FOLLOWING_ERROR_WINDOW = 0x6065
    FOLLOWING_ERROR_TIME_OUT = 0x6066  # U16 ms
    POSITION_WINDOW = 0x6067  # U32 counts (0xFFFFFFFF: off)
    POSITION_WINDOW_TIME = 0x6068  # U16 ms
    VELOCITY_ACTUAL = 0x606C
    TARGET_TORQUE = 0x6071  # I16, per thousand of 0x6076 (CST)
    MAX_TORQUE = 0x6072
    RATED_TORQUE = 0x6076
    TORQUE_ACTUAL = 0x6077
    TARGET_POSITION = 0x607A  # I32, counts (CSP, profile position)
    HOME_OFFSET = 0x607C  # I32 counts: the position actual after homing
    PROFILE_VELOCITY = 0x6081  # U32 counts/s
    PROFILE_ACCELERATION = 0x6083  # U32 counts/s²
    PROFILE_DECELERATION = 0x6084  # U32 counts/s²
    QUICK_STOP_DECELERATION = 0x6085  # U32 counts/s²
    HOMING_METHOD = 0x6098  # I8: 35 or 37 (on the current position)
    TORQUE_OFFSET = 0x60B2  # I16, per thousand of 0x6076 (CSP/CSV/CST feed-forward)
    INTERPOLATION_PERIOD = 0x60C2
    VELOCITY_CONTROL = 0x60F9  # velocity control parameter set (the cascade's velocity PI)
    POSITION_CONTROL = 0x60FB  # position control parameter set (the cascade's position P, feed-forward)
    TARGET_VELOCITY = 0x60FF  # I32 counts/s (CSV)
    SUPPORTED_DRIVE_MODES = 0x6502
    # manufacturer
    REF_POSITION_TABLE = 0x2100
    REF_VELOCITY_TABLE = 0x2101
    FEEDFORWARD_TABLE = 0x2102
    TABLE = 0x2103
    GAINS = 0x2110
    TRIAL = 0x2120
    RECORDER = 0x2200
    RECORDER_DATA = 0x2210
    CONTROL_PERIOD = 0x2300


class InterpolationPeriodSub(IntEnum):
    VALUE = 1  # U8
    INDEX = 2  # I8: period = value · 10^index s


class TableSub(IntEnum):
    LENGTH = 1
    CAPACITY = 2
    LOADED = 3


class GainsSub(IntEnum):
    KP = 1
    KD = 2
    VEL_FILTER = 3
    LOOP = 4  # U8: :class:`LoopStructure`


class LoopStructure(IntEnum):
    """0x2110:4: the drive's feedback (firmware_model.control_law)."""

    PD = 0  # 0x2110:1/2, the paper's loop (the ILC experiments)
    CASCADE = 1  # position P → velocity PI → torque (0x60FB, 0x60F9); robot mode


class VelocityControlSub(IntEnum):
    """0x60F9 velocity control parameter set."""

    KVP = 1  # I32 Q16 µN·m/(count/s)
    KVI = 2  # I32 Q16 µN·m/(count/s)/s


class PositionControlSub(IntEnum):
    """0x60FB position control parameter set."""

    KPP = 1  # I32 Q16 (counts/s)/count
    VELOCITY_FF = 2  # I32 Q16, 65536 = 1.0
    TORQUE_FF = 3  # I32 Q16, 65536 = 1.0


class TrialSub(IntEnum):
    COMMAND = 1
    STATE = 2
    TICKS = 3
    FAULT_CAUSE = 4


class RecorderSub(IntEnum):
    STATUS = 1
    SAMPLES = 2
    CHANNELS = 3
    CAPACITY = 4


class TableLoaded(IntFlag):
    REF_POSITION = 0x1
    REF_VELOCITY = 0x2
    FEEDFORWARD = 0x4
    ALL = 0x7


class TrialCommand(IntEnum):
    DISARM = 0
    ARM = 1


class TrialState(IntEnum):
    """0x2120 sub 2."""

    IDLE = 0
    ARMED = 1
    RUNNING = 2
    DONE = 3
    FAULT = 4


class RecorderStatus(IntEnum):
    """0x2200 sub 1."""

    EMPTY = 0
    RECORDING = 1
    COMPLETE = 2  # the whole trial was recorded
    STOPPED = 3  # trial ended early (fault/abort); samples up to 0x2200:2 are valid


class FaultCause(IntEnum):
    """0x2120 sub 4 and byte 0 of the EMCY manufacturer field."""

    NONE = 0
    FOLLOWING_ERROR = 1
    TICK_SEQUENCE = 2
    HEARTBEAT = 3  #: the host's heartbeat was lost (consumer 0x1016): EMCY 0x8130
    BUS_LOST = 4  #: the bus itself failed (no EMCY possible)
    RPDO_TIMEOUT = 5  #: an RPDO missed its deadline (0x1400+k:5): EMCY 0x8250
    SYNC_LOST = 6  #: no SYNC within 1.5 communication cycle periods (0x1006): EMCY 0x8100
    NMT_ABORT = 7  #: NMT left OPERATIONAL (stop, pre-operational, reset communication) with the power stage on
    CAN_OVERRUN = 8  #: fieldbus frames lost (the receiver overflowed): EMCY 0x8110
    PIL_TARGET = 9  #: the processor-in-the-loop target died or stopped answering: EMCY 0x6100 (:class:`PilFailure`)
    IO_FRAMES_LOST = 10  #: io frames lost (the io receiver overflowed): the tick sequence is broken, EMCY 0x8110


class ModeOfOperation(IntEnum):
    """0x6060 values the drive implements (0x6502 says exactly these)."""

    TABLE_PLAYBACK = -1  # manufacturer-specific: internal PD + feed-forward table playback
    PROFILE_POSITION = 1
    HOMING = 6
    CSP = 8
    CSV = 9
    CST = 10


#: 0x6502 bit of each supported mode (CiA 402: bit 0 pp, 5 hm, 7 csp, 8 csv, 9 cst; bit 16 the
#: manufacturer mode -1)
SUPPORTED_MODE_BITS: Final[dict[ModeOfOperation, int]] = {
    ModeOfOperation.TABLE_PLAYBACK: 1 << 16,
    ModeOfOperation.PROFILE_POSITION: 1 << 0,
    ModeOfOperation.HOMING: 1 << 5,
    ModeOfOperation.CSP: 1 << 7,
    ModeOfOperation.CSV: 1 << 8,
    ModeOfOperation.CST: 1 << 9,
}
#: 0x6502: the supported drive modes (0x000103A1)
SUPPORTED_DRIVE_MODES_VALUE: Final[int] = sum(SUPPORTED_MODE_BITS.values())


class QuickStopOption(IntEnum):
    """0x605A values the drive implements (CiA 402; 3, 4, 7, 8 -- current / voltage limit -- are
    refused: the emulated power stage has no current or voltage limit to brake on)."""

    DISABLE_DRIVE = 0  # torque off at once, Switch on disabled
    SLOW_DOWN_RAMP = 1  # ramp 0x6084, then Switch on disabled
    QUICK_STOP_RAMP = 2  # ramp 0x6085, then Switch on disabled
    SLOW_DOWN_RAMP_STAY = 5  # ramp 0x6084, then stay in Quick stop active (holding)
    QUICK_STOP_RAMP_STAY = 6  # ramp 0x6085, then stay in Quick stop active (holding)


class AbortConnectionOption(IntEnum):
    """0x6007 values: the power stage's reaction to an abort connection (CiA 402)."""

    NO_ACTION = 0
    FAULT = 1
    DISABLE_VOLTAGE = 2
    QUICK_STOP = 3


class ErrorBehaviour(IntEnum):
    """0x1029 sub 1 values: the NMT reaction to a communication error (CiA 301)."""

    PRE_OPERATIONAL = 0  # only if NMT OPERATIONAL
    NO_CHANGE = 1
    STOPPED = 2


class HomingMethod(IntEnum):
    """0x6098 values the drive implements: homing on the current position (no motion)."""

    CURRENT_POSITION_OLD = 35  # CiA 402 before 2016
    CURRENT_POSITION = 37


# ------------------------------------------------------------------ CiA 402 words


class Controlword(IntFlag):
    """0x6040 bits."""

    SWITCH_ON = 0x0001
    ENABLE_VOLTAGE = 0x0002
    QUICK_STOP = 0x0004  # active LOW
    ENABLE_OPERATION = 0x0008
    NEW_SETPOINT = 0x0010  # profile position: rising edge; homing: start
    CHANGE_IMMEDIATELY = 0x0020  # profile position
    RELATIVE = 0x0040  # profile position: 0x607A relative to the last target
    FAULT_RESET = 0x0080  # rising edge
    HALT = 0x0100


class ControlCommand(IntEnum):
    """Controlword values of the device-control commands (docs/canopen-objects.md §5)."""

    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    DISABLE_OPERATION = 0x0007
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080


class Statusword(IntFlag):
    """0x6041 bits."""

    READY_TO_SWITCH_ON = 0x0001
    SWITCHED_ON = 0x0002
    OPERATION_ENABLED = 0x0004
    FAULT = 0x0008
    VOLTAGE_ENABLED = 0x0010
    QUICK_STOP = 0x0020  # active LOW
    SWITCH_ON_DISABLED = 0x0040
    WARNING = 0x0080
    REMOTE = 0x0200
    TARGET_REACHED = 0x0400
    INTERNAL_LIMIT = 0x0800
    FOLLOWS_COMMAND = 0x1000  # cyclic synchronous modes
    SETPOINT_ACKNOWLEDGE = 0x1000  # profile position
    HOMING_ATTAINED = 0x1000  # homing
    FOLLOWING_ERROR = 0x2000  # PP, CSP: |e| > 0x6065, not yet longer than 0x6066 (then a fault)


class Cia402State(IntEnum):
    """CiA 402 power states."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


#: (mask, value) of the statusword for each state, exactly as the CiA 402 table
STATUSWORD_PATTERN: Final[dict[Cia402State, tuple[int, int]]] = {
    Cia402State.NOT_READY_TO_SWITCH_ON: (0x004F, 0x0000),
    Cia402State.SWITCH_ON_DISABLED: (0x004F, 0x0040),
    Cia402State.READY_TO_SWITCH_ON: (0x006F, 0x0021),
    Cia402State.SWITCHED_ON: (0x006F, 0x0023),
    Cia402State.OPERATION_ENABLED: (0x006F, 0x0027),
    Cia402State.QUICK_STOP_ACTIVE: (0x006F, 0x0007),
    Cia402State.FAULT_REACTION_ACTIVE: (0x004F, 0x000F),
    Cia402State.FAULT: (0x004F, 0x0008),
}


def state_from_statusword(statusword: int) -> Cia402State:
    """Decode the CiA 402 state from a statusword (masks of the CiA 402 table).

    :raises ValueError: the bits match no state.
    """
    # the 0x6F patterns first: they are more specific than the 0x4F ones
    order = sorted(STATUSWORD_PATTERN.items(), key=lambda kv: -kv[1][0])
    for state, (mask, value) in order:
        if statusword & mask == value:
            return state
    raise ValueError(f"statusword 0x{statusword:04X} matches no CiA 402 state")


# ------------------------------------------------------------------ constants

#: node ids of the robot's four drives, joint j = 1..4 is node j
DRIVE_NODE_IDS: Final[tuple[int, ...]] = (1, 2, 3, 4)
#: the drive's electronic data sheet (describes every object above)
DRIVE_EDS_PATH: Final[Path] = Path(__file__).resolve().parent / "drive.eds"

#: CiA 301 device type: 0x0192 = 402 profile, 0x0002 = servo drive
DEVICE_TYPE_VALUE: Final[int] = 0x00020192
#: 0x1018:1 vendor-ID.  CiA assigns every CANopen vendor-ID (can-cia.org, "CANopen vendor-ID");
#: this project has none, so the drive carries a value from the range CiA does not assign
#: (0xAFFF0000..0xFFFEFFFF is reserved): it can never name a real manufacturer.  Replace it with
#: the project's own ID once CiA assigns one (docs/canopen-objects.md §5.1).
VENDOR_ID: Final[int] = 0xAFFF0402
#: 0x1018:2 product code and :3 revision (major.minor in the high/low 16 bits)
PRODUCT_CODE: Final[int] = 0x00000402
REVISION_NUMBER: Final[int] = 0x00020000
#: 0x1010/0x1011 signatures: "save" and "load" as little-endian U32 (CiA 301 §7.5.2.14/15)
STORE_SIGNATURE: Final[int] = 0x65766173
RESTORE_SIGNATURE: Final[int] = 0x64616F6C
#: 0x6076 default: joint-side rated torque in mN·m (88.2 N·m)
RATED_TORQUE_MNM: Final[int] = 88_200
#: 0x6072 default and EDS HighLimit: max torque in per-thousand of rated (3000 -> 264.6 N·m,
#: the motor's peak rating; more is refused with 0x06090031)
MAX_TORQUE_PERMILLE: Final[int] = 3000
#: 0x2300 default control period, µs
CONTROL_PERIOD_US: Final[int] = 1000
#: 0x2103 sub 2: table and recorder capacity, samples (60 s at 1 kHz)
TABLE_CAPACITY: Final[int] = 60_000
#: recorder channels (planes)
RECORDER_CHANNELS: Final[int] = 4
#: 0x6065 value that disables the following-error check
FOLLOWING_ERROR_OFF: Final[int] = 0xFFFFFFFF
#: 0x6065 default, counts (≈ 0.6 rad)
FOLLOWING_ERROR_DEFAULT: Final[int] = 1_000_000


# ------------------------------------------------------------------ table packing


class TablePackingError(ValueError):
    """Bytes or values that do not form an int32 table."""


def u8(v: int) -> bytes:
    """UNSIGNED8 as the SDO payload (little endian)."""
    return struct.pack("<B", v)


def u16(v: int) -> bytes:
    """UNSIGNED16 as the SDO payload (little endian)."""
    return struct.pack("<H", v)


def u32(v: int) -> bytes:
    """UNSIGNED32 as the SDO payload (little endian)."""
    return struct.pack("<I", v)


def i32(v: int) -> bytes:
    """INTEGER32 as the SDO payload (little endian)."""
    return struct.pack("<i", v)


def pack_int32(values: npt.ArrayLike) -> bytes:
    """Pack integers as little-endian int32 bytes.

    :raises TablePackingError: a value is outside int32 or not integral.
    """
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise TablePackingError(f"expected a 1-D table, got shape {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise TablePackingError(f"expected integers, got dtype {arr.dtype}")
    a64 = arr.astype(np.int64)
    if a64.size and (a64.min() < -(1 << 31) or a64.max() > (1 << 31) - 1):
        raise TablePackingError("table value outside int32")
    return a64.astype("<i4").tobytes()


def unpack_int32(data: bytes) -> npt.NDArray[np.int32]:
    """Unpack little-endian int32 bytes (a copy, native int32).

    :raises TablePackingError: length not a multiple of 4.
    """
    if len(data) % 4:
        raise TablePackingError(f"{len(data)} bytes is not a whole number of int32")
    return np.frombuffer(data, dtype="<i4").astype(np.int32)


def unpack_recorder(data: bytes, n_samples: int) -> npt.NDArray[np.int32]:
    """Split recorder DOMAIN bytes into a (RECORDER_CHANNELS, n_samples) int32 array.

    :raises TablePackingError: length is not RECORDER_CHANNELS · 4 · n_samples.
    """
    expected = RECORDER_CHANNELS * 4 * n_samples
    if len(data) != expected:
        raise TablePackingError(f"recorder data is {len(data)} bytes, expected {expected}")
    return unpack_int32(data).reshape(RECORDER_CHANNELS, n_samples)

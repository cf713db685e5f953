"""Type stub of the C extension firmware_model/_fwcore.c (the drive firmware's C core, firmware_model/c/)."""

from firmware_model.control_law import RecorderArray, StateArray, TableArray

# every constant of firmware_model/c/ilc_drive.h without its ILC_ prefix (the ones used from Python)
N_STATE: int
ACC_Q: int
GAIN_Q: int
VEL_FILTER_Q: int
VEL_STATE_Q: int
RATE_Q: int
STATUS_OK: int
STATUS_FOLLOWING_ERROR: int
LOOP_PD: int
LOOP_CASCADE: int

def control_tick(
    count: int, idx: int, rec_idx: int, st: StateArray, tables: TableArray, rec: RecorderArray
) -> tuple[int, int]: ...
def rshift_round(x: int, q: int) -> int: ...
def csp_velocity_ref(target: int, prev: int, rate_q12: int) -> int: ...
def velocity_from_tick_q16(v_q16: int, period_us: int) -> int: ...
def torque_units_to_permille(tau_units: int, rated_mnm: int) -> int: ...

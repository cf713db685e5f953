"""Type stub of the C extension firmware_model/_fwcore.c (the drive firmware's C core, firmware_model/c/)."""

from collections.abc import Callable, Sequence

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

class TrialTicker:
    """A drive's plain io ticks of a trial in table playback, outside the interpreter
    (firmware_model/plain_ticks.py, firmware_model/_fwcore.c)."""

    armed: bool
    ticks: int
    def __init__(
        self,
        fallback: Callable[[int, bytes], Sequence[tuple[int, bytes]] | None],
        clock: Callable[[], float],
        kernel: Callable[..., tuple[int, int]],
        node: object,
        drive: object,
        trial: object,
        torque_id: int,
    ) -> None: ...
    def arm(
        self,
        st: StateArray,
        tables: TableArray,
        rec: RecorderArray,
        next_tick: int,
        n_table: int,
        next_full_tick: int,
        tick_origin: int,
        time_us: int,
        period_us: int,
        offset: int,
        frames_out: int,
        serve_by_s: float,
        status_base: int,
        status_limited: int,
    ) -> None: ...
    def disarm(self) -> None: ...
    def __call__(self, index: int, data: bytes) -> Sequence[tuple[int, bytes]] | None: ...

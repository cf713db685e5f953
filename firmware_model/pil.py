"""Processor in the loop: the drive's control period run by the C firmware on an emulated Cortex-M4.

Owns :class:`PilKernel`, a callable with the signature of
:func:`firmware_model.control_law.control_tick` (``(count, idx, rec_idx, st, tables, rec) ->
(torque µN·m, status)``) whose arithmetic runs in ``ilc_control_tick`` on QEMU's ``mps2-an386``
(:mod:`firmware_model.pil_link`, image from :mod:`firmware_model.pil_build`), and
:func:`pil_control_tick`, the ``"pil"`` branch of ``firmware_model.firmware_select``.

What crosses the link each period (the target keeps st[], the tables and the recorder in its RAM):

* **to the target**: the st[] words that differ from what the target holds (the drive's
  parameter writes and the Python side's own resets of loop state since the last period), the
  table column ``idx`` if the target's copy of it differs (a download or a set-point written since
  it was last played), and the period's count, idx and rec_idx;
* **back**: torque, status, the st[] words the step changed (written into the caller's ``st``),
  the recorder column (written into the caller's ``rec``) and the step's instruction count.

So after each call ``st`` and ``rec`` hold exactly what the numba kernel would have left there.
The instruction counts of the steps are kept per loop structure (:attr:`PilKernel.stats`: PD loop
and cascade), at SysTick's resolution of 40 instructions (an instruction count under QEMU's
``-icount shift=0``, not silicon cycles).

May import: bus, firmware_model.control_law, firmware_model.pil_build, firmware_model.pil_link.
"""

from __future__ import annotations

import atexit
import logging
from dataclasses import dataclass

from bus.pil_fault import PilFailure
from firmware_model import control_law
from firmware_model.control_law import RecorderArray, StateArray, TableArray
from firmware_model.pil_build import build_image, missing_tools, require_tools
from firmware_model.pil_link import TICK, TICK_COLUMN, TICK_REPLY, PilError, PilTarget, get_s, get_u, put_s, put_u, wrap64

logger = logging.getLogger(__name__)

__all__ = ["InstructionStats", "PilError", "PilKernel", "missing_tools", "pil_control_tick", "require_tools"]

_N_STATE = control_law.N_STATE
_P_LOOP = control_law.P_LOOP
#: loop structure names of the statistics (st[P_LOOP] values)
LOOP_NAMES = {control_law.LOOP_PD: "pd", control_law.LOOP_CASCADE: "cascade"}
#: (recorder row, the st word it is sent relative to) -- pil_protocol.h
_REC_STATE_SLOTS = (
    (control_law.REC_POS, control_law.S_POS),
    (control_law.REC_VEL, control_law.S_VEST),
    (control_law.REC_TAU, control_law.S_TAU),
    (control_law.REC_TAU_FB, control_law.S_TAU_FB),
)


@dataclass
class InstructionStats:
    """Instructions per control period of one loop structure (SysTick-measured, 40-instruction
    resolution): periods, sum, largest."""

    periods: int = 0
    total: float = 0.0
    largest: float = 0.0

    @property
    def mean(self) -> float:
        return self.total / self.periods if self.periods else 0.0

    def add(self, instructions: float) -> None:
        self.periods += 1
        self.total += instructions
        if instructions > self.largest:
            self.largest = instructions


class PilKernel:
    """The control kernel on a PIL target (see the module docstring).

    :param target: a started :class:`firmware_model.pil_link.PilTarget` (closed by :meth:`close`)
    """

    def __init__(self, target: PilTarget) -> None:
        self.target = target
        self._st: list[int] = [0] * _N_STATE  # what the target's st[] holds (it boots zeroed)
        self._cols: dict[int, tuple[int, int, int]] = {}  # the target's table columns (zero unless here)
        # the "previous" values of the TICK coding (pil_protocol.h)
        self._prev_idx = 0
        self._prev_count = 0
        self._prev_col = (0, 0, 0)
        self._table_cols = target.info.table_cols
        self._rec_cols = target.info.rec_cols
        self._per_tick = target.info.instructions_per_tick
        #: instructions per period by loop structure (LOOP_NAMES)
        self.stats: dict[str, InstructionStats] = {}
        #: the failure that stopped the target (every later period raises it again at once)
        self.failed: PilError | None = None

    def __call__(
        self, count: int, idx: int, rec_idx: int, st: StateArray, tables: TableArray, rec: RecorderArray
    ) -> tuple[int, int]:
        """One control period on the target; same contract as ``control_law.control_tick``.

        :raises PilError: the target failed (a drive fault: the message says which and where,
            ``failure`` what happened); the target is then stopped and every later call raises
            the same failure at once, without touching the link
        """
        if self.failed is not None:
            raise PilError(str(self.failed), self.failed.failure)
        try:
            return self._step(count, idx, rec_idx, st, tables, rec)
        except PilError as err:
            failed = err
        except IndexError:  # a reply shorter than its contents
            failed = PilError(f"{self.target.label}: a truncated TICK reply", PilFailure.PROTOCOL)
        self.failed = failed
        self.target.close()
        raise failed

    def _step(
        self, count: int, idx: int, rec_idx: int, st: StateArray, tables: TableArray, rec: RecorderArray
    ) -> tuple[int, int]:
        """One period over the link (:meth:`__call__` without the failure bookkeeping)."""
        idx = int(idx)
        rec_idx = int(rec_idx)
        if not 0 <= idx < self._table_cols:
            raise PilError(f"{self.target.label}: table column {idx} beyond the target's {self._table_cols}")
        if rec_idx >= self._rec_cols:
            raise PilError(f"{self.target.label}: recorder column {rec_idx} beyond the target's {self._rec_cols}")
        out = bytearray()
        now = st.tolist()
        held = self._st
        if now != held:
            writes = [i for i in range(_N_STATE) if now[i] != held[i]]
            put_u(out, len(writes))
            for i in writes:
                out.append(i)
                put_s(out, now[i])
        else:
            out.append(0)
        column = (int(tables[0, idx]), int(tables[1, idx]), int(tables[2, idx]))
        send_column = self._cols.get(idx, (0, 0, 0)) != column
        out.append(TICK_COLUMN if send_column else 0)
        put_s(out, idx - self._prev_idx)
        put_u(out, 0 if rec_idx < 0 else (1 if rec_idx == idx else rec_idx + 2))
        count = int(count)
        put_s(out, wrap64(count - self._prev_count))
        if send_column:
            last = self._prev_col
            put_s(out, column[0] - last[0])
            put_s(out, column[1] - last[1])
            put_s(out, column[2] - last[2])

        kind, body = self.target.exchange(TICK, out)
        if kind != TICK_REPLY:
            raise PilError(f"{self.target.label}: TICK answered with frame {chr(kind)!r}")
        self._prev_idx = idx
        self._prev_count = wrap64(count)
        if send_column:
            self._prev_col = column
            self._cols[idx] = column
        tau, pos = get_s(body, 0)
        status, pos = get_u(body, pos)
        n_changed, pos = get_u(body, pos)
        for _ in range(n_changed):
            slot = body[pos]
            delta, pos = get_s(body, pos + 1)
            value = wrap64(now[slot] + delta)
            now[slot] = value
            st[slot] = value
        self._st = now
        if rec_idx >= 0:
            for row, slot in _REC_STATE_SLOTS:
                delta, pos = get_s(body, pos)
                rec[row, rec_idx] = now[slot] + delta
        ticks, pos = get_u(body, pos)
        if pos != len(body):
            raise PilError(f"{self.target.label}: TICK reply of {len(body)} bytes, {pos} expected")
        loop = LOOP_NAMES.get(now[_P_LOOP], "other")  # a parameter: the step does not change it
        stats = self.stats.get(loop)
        if stats is None:
            stats = self.stats[loop] = InstructionStats()
        stats.add(ticks * self._per_tick)
        return tau, status

    def summary(self) -> str:
        """The instruction counts so far, one phrase per loop structure."""
        return "; ".join(
            f"{name}: {s.periods} periods, mean {s.mean:.0f}, max {s.largest:.0f} instructions"
            for name, s in sorted(self.stats.items())
        )

    def close(self) -> None:
        """Log the instruction counts and stop the target (idempotent)."""
        if self.stats:
            logger.info("%s: %s", self.target.label, self.summary())
            self.stats = {}
        self.target.close()


_KERNELS: list[PilKernel] = []


def _close_all() -> None:
    for kernel in _KERNELS:
        kernel.close()
    _KERNELS.clear()


def pil_control_tick(node_id: int) -> PilKernel:
    """The control kernel of drive ``node_id`` on its own PIL target: builds the image (cached),
    starts QEMU as this process's child and returns a :class:`PilKernel` (stopped at exit).

    :raises InputError: the cross toolchain or QEMU is missing (one line naming the apt packages)
    :raises PilError: QEMU did not start or answer
    """
    kernel = PilKernel(PilTarget(build_image(), label=f"node {int(node_id)} PIL target"))
    if not _KERNELS:
        atexit.register(_close_all)
    _KERNELS.append(kernel)
    return kernel

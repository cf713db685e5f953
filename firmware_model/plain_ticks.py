"""A trial's plain io ticks of a drive, run by the firmware's C core outside the interpreter.

This module owns when a drive's io tick is *plain* and :class:`PlainTicks`, which hands such
ticks to :class:`firmware_model._fwcore.TrialTicker` (firmware_model/_fwcore.c).  The hub
client's answer loop (:class:`bus.cia301.answering.AnsweringNode`, ``bus/transports/hub/_hubcore.c``)
reads a drive's encoder frames in C and calls a callback per frame; the drive node's callback is
the firmware's Python path (:meth:`firmware_model.drive_node.DriveNode._answer_tick`), or, while the
ticks are plain, the ticker, which runs the same integer steps without a Python frame: the wire
tick widened, the control period of :meth:`firmware_model.drive.Drive.io_tick` in table playback
(:class:`firmware_model.modes.TablePlaybackMode`) with the drive's own kernel (the Python model's
numba kernel, or with ``--firmware c`` the C core's :c:func:`ilc_control_tick` itself), the torque
frame and its status; and it writes back what that path changes (``drive.time_us``,
``trial.next_tick``, the node's next tick and frame count), so the Python side reads the same
state whichever ran a tick.

A tick is plain when, at the moment the loop starts (:meth:`PlainTicks.on_frame`):

* the drive plays a running trial in table playback, not yet at its last tick, with torque on and
  no quick stop, with a kernel the ticker can run (not processor in the loop);
* the tick leaves the PDO side nothing to do (:meth:`firmware_model.cyclic_pdo.CyclicPdo.quiet_ticks`:
  no SYNC credit, no TPDO sampled or waiting, no event-driven TPDO, no RPDO deadline) and no EMCY
  waits;
* the node holds no encoder frame and no fieldbus frame waits behind a SYNC.

Nothing but the Python path changes those, and the ticker disarms itself before it calls that
path: the ticker hands a frame over unchanged when the tick is out of sequence, is the trial's
last, comes at or after the service's deadline, or ends in a kernel status (a following error:
the ticker puts the state and the recorder column back first, and the Python path runs the same
tick from the same state).  So traces, frames and faults are those of the Python path
(tests/test_plain_ticks.py).  ``ILCRIG_PLAIN_TICKS=python`` (:data:`PLAIN_TICKS_ENV`) leaves
every tick to the Python path, as a build without the C core does.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from bus.bus_features import FrameAnswer
from firmware_model import control_law
from firmware_model.firmware_select import c_available
from firmware_model.modes import TablePlaybackMode
from firmware_model.playback import TrialState

if TYPE_CHECKING:
    from firmware_model.drive import Drive

logger = logging.getLogger(__name__)

__all__ = ["PLAIN_TICKS_ENV", "PlainTicks", "plain_ticks_enabled", "plain_ticks_for"]

#: ``python``: every io tick through the firmware's Python path (A/B measurements, tests)
PLAIN_TICKS_ENV: str = "ILCRIG_PLAIN_TICKS"

_RUNNING = TrialState.RUNNING


def plain_ticks_enabled() -> bool:
    """The C core is built and :data:`PLAIN_TICKS_ENV` does not say ``python``."""
    if os.environ.get(PLAIN_TICKS_ENV, "c").strip().lower() == "python":
        return False
    return c_available()


def _kernels() -> tuple[Any, ...]:
    """The kernels the ticker runs: the Python model's, and the C core's where it is built."""
    from firmware_model import _fwcore

    return (control_law.control_tick, _fwcore.control_tick)


def plain_ticks_for(
    drive: object,
    fallback: FrameAnswer,
    clock: Callable[[], float],
    node: object,
    torque_id: int,
    torque_status: Callable[[], int],
) -> PlainTicks | None:
    """:class:`PlainTicks` for a node of ``drive`` where they can run (a
    :class:`firmware_model.drive.Drive` with a kernel the ticker runs, :func:`plain_ticks_enabled`),
    else None (the arguments are :class:`PlainTicks`'s)."""
    from firmware_model.drive import Drive

    if not isinstance(drive, Drive) or not plain_ticks_enabled():
        return None
    if not any(drive.motion.mode.control_tick is k for k in _kernels()):
        return None  # processor in the loop: its kernel talks to the target
    return PlainTicks(drive, fallback, clock, node, torque_id, torque_status)


class PlainTicks:
    """The plain ticks of one drive node (module docstring).

    :param drive: the node's firmware
    :param fallback: the node's Python path for an encoder frame, ``(index, data) -> answers | None``
    :param clock: the node's clock [s] (its service's deadline is on it)
    :param node: the drive node (the ticker writes its ``_next_full_tick`` and ``frames_out``)
    :param torque_id: the joint's torque frame identifier
    :param torque_status: the node's torque frame status now (:meth:`DriveNode._torque_status`)
    """

    def __init__(
        self,
        drive: Drive,
        fallback: FrameAnswer,
        clock: Callable[[], float],
        node: object,
        torque_id: int,
        torque_status: Callable[[], int],
    ) -> None:
        from firmware_model import _fwcore

        self._drive = drive
        self._fallback = fallback
        self._status = torque_status
        kernel = drive.motion.mode.control_tick  # every mode's: the drive's firmware (MotionContext)
        self._ticker = _fwcore.TrialTicker(fallback, clock, kernel, node, drive, drive.trial, torque_id)

    @property
    def ticks(self) -> int:
        """Ticks the ticker ran."""
        return int(self._ticker.ticks)

    def on_frame(self, next_full_tick: int, tick_origin: int, frames_out: int, serve_by_s: float) -> FrameAnswer:
        """The callback for the answer loop starting now: the ticker, armed, while the drive's
        ticks are plain (module docstring), else the Python path. The arguments are the node's
        (its next tick, the trial's wire origin, its frames sent, its service's deadline)."""
        drive = self._drive
        trial = drive.trial
        mode = drive.motion.mode
        power = drive.power
        if (
            trial.state != _RUNNING
            or trial.next_tick + 1 >= trial.n_table
            or type(mode) is not TablePlaybackMode
            or not power.on
            or power.quick_stopping
            or power.emcy_pending
            or not drive.tick_ready
            or not drive.pdo.quiet_ticks()
        ):
            return self._fallback
        st = mode.st
        limited = int(st[control_law.S_LIMITED])
        try:  # the torque status with and without the internal limit, the rest of the state as now
            st[control_law.S_LIMITED] = 0
            status_base = self._status()
            st[control_law.S_LIMITED] = 1
            status_limited = self._status()
        finally:
            st[control_law.S_LIMITED] = limited
        self._ticker.arm(
            st,
            trial.tables,
            trial.rec,
            trial.next_tick,
            trial.n_table,
            next_full_tick,
            tick_origin,
            drive.time_us,
            mode.period_us(),
            drive.motion.offset,
            frames_out,
            serve_by_s,
            status_base,
            status_limited,
        )
        return self._ticker

    def disarm(self) -> None:
        """Every frame to the Python path (the node's state may change now)."""
        self._ticker.disarm()

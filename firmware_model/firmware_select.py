"""Which implementation of the drive's control period a drive runs: ``--firmware {python,c,pil}``.

This module owns the names of the firmwares (:data:`FIRMWARES`), their check before anything
starts (:func:`check_firmware`: a bad name, or ``c`` without the built extension, is one
:class:`bus.errors.InputError`) and the kernel of one drive (:func:`control_tick_for`), which
:class:`firmware_model.drive.Drive` passes to its operation modes:

* ``python`` -- the reference model, the numba kernel
  :func:`firmware_model.control_law.control_tick`;
* ``c`` -- the C core firmware_model/c/ilc_control.c (interface firmware_model/c/ilc_drive.h)
  built for the host as the extension :mod:`firmware_model._fwcore` by setup.py (software in the
  loop; bit-exact with ``python``, tests/test_firmware_c.py);
* ``pil`` -- processor in the loop: the same C sources cross-compiled for a Cortex-M4F and run
  on QEMU's ``mps2-an386``, one emulator per drive, one request/reply per control period over
  the board's UART (:mod:`firmware_model.pil`; needs ``arm-none-eabi-gcc`` and
  ``qemu-system-arm``, checked by :func:`_pil_check`).

Every kernel has the signature and the semantics of :data:`ControlTick`.  The other integer steps
of the period (:class:`PeriodSteps`: the CSP velocity reference, a profile velocity in counts/s,
the torque actual 0x6077 in ‰) come with the firmware too (:func:`period_steps_for`): the Python
model for ``python``, the C core's functions of the host build for ``c``; with ``pil`` they run on
the host (the protocol carries one period's kernel call), in that same host build of the C core
where it is built, otherwise in the Python model.  Kept import-light (the
command line imports it to check ``--firmware``): numpy, numba and the extension are imported
when a kernel is asked for.

May import: ``bus`` (and ``firmware_model``'s own modules, lazily).
"""

from __future__ import annotations

import importlib.util
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeAlias

from bus.errors import InputError

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

logger = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_FIRMWARE",
    "FIRMWARES",
    "ControlTick",
    "PeriodSteps",
    "c_available",
    "check_firmware",
    "control_tick_for",
    "period_steps_for",
]

#: the firmwares a drive can run (``--firmware``), the first is the default
FIRMWARES: tuple[str, ...] = ("python", "c", "pil")
DEFAULT_FIRMWARE: str = "python"

#: one control period: ``(count, idx, rec_idx, st, tables, rec) -> (torque µN·m, status)``, as
#: :func:`firmware_model.control_law.control_tick`
ControlTick: TypeAlias = Callable[
    [int, int, int, "npt.NDArray[np.int64]", "npt.NDArray[np.int32]", "npt.NDArray[np.int32]"], tuple[int, int]
]


def c_available() -> bool:
    """The C core's extension :mod:`firmware_model._fwcore` is built in this installation."""
    return importlib.util.find_spec("firmware_model._fwcore") is not None


def _pil_check() -> None:
    """Processor in the loop can run here: the cross compiler and QEMU are on PATH.

    :raises InputError: one of them is missing (one line naming the apt packages)."""
    from firmware_model.pil_build import require_tools

    require_tools()


def _pil_control_tick(node_id: int) -> ControlTick:
    """The processor-in-the-loop kernel of drive ``node_id``: its own QEMU, started now as this
    process's child (:func:`firmware_model.pil.pil_control_tick`)."""
    from firmware_model.pil import pil_control_tick

    kernel: ControlTick = pil_control_tick(node_id)
    return kernel


def check_firmware(kind: str) -> str:
    """``kind`` if this installation can run it, before any process starts.

    :raises InputError: not one of :data:`FIRMWARES`, ``c`` without the built extension, or
        ``pil`` where processor in the loop cannot run (one line each)."""
    if kind not in FIRMWARES:
        raise InputError(f"--firmware: must be one of {', '.join(FIRMWARES)}, got {kind!r}")
    if kind == "c" and not c_available():
        raise InputError(
            "--firmware: c needs the C firmware (extension firmware_model._fwcore), which is not built in this "
            "installation (reinstall with a C compiler: pip install -e .)"
        )
    if kind == "pil":
        _pil_check()
    return kind


def control_tick_for(kind: str, node_id: int) -> ControlTick:
    """The control-period kernel drive ``node_id`` runs with firmware ``kind``.

    :raises InputError: as :func:`check_firmware`."""
    check_firmware(kind)
    if kind == "c":
        from firmware_model import _fwcore

        return _fwcore.control_tick
    if kind == "pil":
        return _pil_control_tick(node_id)
    from firmware_model import control_law

    return control_law.control_tick


@dataclass(frozen=True)
class PeriodSteps:
    """The pure integer steps of a control period besides its kernel (each the same function, bit
    for bit, in the Python model and in firmware_model/c/ilc_control.c):

    :ivar csp_velocity_ref: ``(target, previous target [counts], rate Q12) -> counts/s``, CSP's
        velocity reference (``ilc_csp_velocity_ref``)
    :ivar velocity_from_tick_q16: ``(v [counts/tick Q16], period [µs]) -> counts/s``, a profile
        velocity as the loop's reference (``ilc_velocity_from_tick_q16``)
    :ivar torque_units_to_permille: ``(torque [µN·m], rated torque [mN·m]) -> ‰``, the torque
        actual 0x6077 (``ilc_torque_units_to_permille``)
    :ivar where: which implementation: ``"python"`` or ``"c"``
    """

    csp_velocity_ref: Callable[[int, int, int], int]
    velocity_from_tick_q16: Callable[[int, int], int]
    torque_units_to_permille: Callable[[int, int], int]
    where: str


def _python_steps() -> PeriodSteps:
    from bus import fixedpoint as fp
    from firmware_model import control_law

    return PeriodSteps(control_law.csp_velocity_ref, fp.velocity_from_tick_q16, fp.torque_units_to_permille, "python")


def _c_steps() -> PeriodSteps:
    from firmware_model import _fwcore

    return PeriodSteps(_fwcore.csp_velocity_ref, _fwcore.velocity_from_tick_q16, _fwcore.torque_units_to_permille, "c")


def period_steps_for(kind: str) -> PeriodSteps:
    """The period's other integer steps with firmware ``kind`` (see the module docstring): C for
    ``c``, and for ``pil`` where the host build of the C core exists; the Python model otherwise.

    :raises InputError: ``kind`` is not one of :data:`FIRMWARES`, or ``c`` without the extension."""
    if kind not in FIRMWARES:
        raise InputError(f"--firmware: must be one of {', '.join(FIRMWARES)}, got {kind!r}")
    if kind == "c":
        check_firmware(kind)
        return _c_steps()
    if kind == "pil" and c_available():
        return _c_steps()
    return _python_steps()

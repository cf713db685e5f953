"""The errors of planning.

All subclass :class:`bus.errors.InputError` (a ``ValueError``; the CLI maps it to exit code 2):
:class:`TrajectoryError` (bad arguments, internal planning failure) and
:class:`InfeasibleTaskError` (the task cannot be done within the limits).  Reach failures are the
plant's ``OutOfReachError``, re-raised with the sample time and the point
(:func:`host.planning.joint_reference.joint_reference`).

May import: ``bus`` only.
"""

from __future__ import annotations

from bus.errors import InputError

__all__ = ["InfeasibleTaskError", "TrajectoryError"]


class TrajectoryError(InputError):
    """Bad planning arguments or an internal planning failure (one-line message)."""


class InfeasibleTaskError(InputError):
    """The task cannot be executed within the kinematic, joint or torque limits."""

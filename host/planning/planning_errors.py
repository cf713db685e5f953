"""The errors of planning.

All subclass ``ValueError`` (the CLI maps them to exit code 2) and :class:`bus.errors.IlcrigError`:
:class:`TrajectoryError` (bad arguments, internal planning failure) and
:class:`InfeasibleTaskError` (the task cannot be done within the limits).  Reach failures are the
plant's ``OutOfReachError``, re-raised with the sample time and the point
(:func:`host.planning.joint_reference.joint_reference`).

May import: ``bus`` only.
"""

from __future__ import annotations

from bus.errors import IlcrigError

__all__ = ["InfeasibleTaskError", "TrajectoryError"]


class TrajectoryError(IlcrigError, ValueError):
    """Bad planning arguments or an internal planning failure (one-line message)."""


class InfeasibleTaskError(IlcrigError, ValueError):
    """The task cannot be executed within the kinematic, joint or torque limits."""

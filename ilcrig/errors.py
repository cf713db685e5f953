"""The exceptions of the public API.

This module owns :class:`InputError` (bad input: the one-line message the command line prints after
``ilcrig: error:``, raised before anything moves) and :class:`RigError` (the rig could not be started
or ended in a way that leaves no results).  A fault during a run is not an exception: it ends the run
and is in :attr:`ilcrig.Results.fault`.
"""

from __future__ import annotations

import logging

from bus.errors import InputError

logger = logging.getLogger(__name__)

__all__ = ["InputError", "RigError", "input_error"]


class RigError(RuntimeError):
    """The rig could not be started (``ilcrig run`` exit code 4) or ended without results."""


def input_error(exc: BaseException) -> InputError:
    """The :class:`InputError` of a ``ValueError`` / ``FileNotFoundError`` of the internals: its first
    line, as the command line prints it."""
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return InputError(text)

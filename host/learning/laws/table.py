"""The static table of the project's laws: name → class.

This module owns :data:`PROJECT_LAWS`, every law ilcrig itself ships (the eight classic laws and
``cno-ilc``, ``adjoint-ilc``).  The names are :data:`host.learning.names.PROJECT_LAW_NAMES` (checked
here at import); they resolve from this table alone, whatever is installed: no plug-in and no
registered class may take one (:mod:`host.learning.registry`).  Entry points of the group
``ilcrig.laws`` are for third parties only.

May import: the law modules of :mod:`host.learning.laws` and :mod:`host.learning.names`.
"""

from __future__ import annotations

import logging
from typing import Any

from host.learning.laws.adjoint import AdjointGradient
from host.learning.laws.constrained import ConstrainedNormOptimal
from host.learning.laws.norm_optimal import NoIlc, NoIlcId
from host.learning.laws.pd import DIlc, PdIlc, PdIlcQ, PdOl, POl, QIlc
from host.learning.names import PROJECT_LAW_NAMES

logger = logging.getLogger(__name__)

__all__ = ["PROJECT_LAWS"]

#: every project law: name → class (each class's ``name`` attribute is its key)
PROJECT_LAWS: dict[str, type[Any]] = {
    cls.name: cls for cls in (PdIlc, PdIlcQ, PdOl, POl, DIlc, QIlc, NoIlc, NoIlcId, ConstrainedNormOptimal, AdjointGradient)
}
if tuple(PROJECT_LAWS) != PROJECT_LAW_NAMES:  # pragma: no cover - a programming error, caught by every test
    raise ImportError(f"PROJECT_LAWS {list(PROJECT_LAWS)} differs from host.learning.names.PROJECT_LAW_NAMES {PROJECT_LAW_NAMES}")

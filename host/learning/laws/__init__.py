"""host.learning.laws: every law of the project, one home.

Owns, one concern per module:

* :mod:`host.learning.laws.base` — :class:`LawContext` (what every law is built with) and
  ``BuiltinLaw``, the base class of the classic laws: ``update(trial)`` of the public protocol over
  the law's fixed arithmetic ``_update(u, e, tau)``;
* :mod:`host.learning.laws.pd` — the PD-type laws ``pd-ilc``, ``pd-ilc-q``, ``pd-ol``, ``p-ol``,
  ``d-ilc``, ``q-ilc``;
* :mod:`host.learning.laws.norm_optimal` — ``no-ilc`` and ``no-ilc-id``;
* :mod:`host.learning.laws.constrained` — ``cno-ilc``, constrained norm-optimal ILC (a QP, OSQP);
* :mod:`host.learning.laws.adjoint` — ``adjoint-ilc``, model-free gradient ILC with auxiliary rollouts;
* :mod:`host.learning.laws.table` — ``PROJECT_LAWS``, the static table name → class;
* :mod:`host.learning.laws.checked` — ``CheckedLaw``, the one checked wrapper every law runs in
  (project law or plug-in), ``LawError`` and ``build_law``.

Every law implements the public protocol (:class:`host.learning.protocol.LawProtocol`, re-exported
as ``ilcrig.LearningLaw``).  This ``__init__`` stays import-light (it re-exports nothing that pulls
in the laws): import from the modules.

May import: what :mod:`host.learning` may import (``bus``, ``plant``, :mod:`host.planning`) and the
rest of :mod:`host.learning`.  Never ``ilcrig``.
"""

from __future__ import annotations

from host.learning.laws.base import LawContext

__all__ = ["LawContext"]

"""ilcrig's own learning laws beyond the built-in ones, written against the public protocol
(:class:`ilcrig.LearningLaw`) and registered as plug-ins (entry-point group ``ilcrig.laws`` in
ilcrig's ``pyproject.toml``).

Owns :mod:`ilcrig.laws.constrained` (``cno-ilc``: constrained norm-optimal ILC, a QP per trial with
the joint torque limit as constraints, OSQP) and :mod:`ilcrig.laws.adjoint` (``adjoint-ilc``:
model-free gradient ILC by the adjoint experiment, two auxiliary rollouts per learning step).
May import what :mod:`ilcrig` may import (they use :mod:`host.learning` for the closed-loop model
and the identification).
"""

"""host.learning: the iterative learning laws.

Owns, one concern per module:

* :mod:`host.learning.names` — the law names, the default law, the preset names and the largest
  number of trials (import-light: the command line reads them);
* :mod:`host.learning.gains` — the gains, their presets and their normalisation to the plant;
* :mod:`host.learning.signals` — lead, backward difference and the zero-phase Q filter, each with
  its transpose;
* :mod:`host.learning.model` — the closed loop linearised along the reference as a time-varying
  state-space model: G, Gᵀ and the drive's feedback K applied in O(N);
* :mod:`host.learning.norm_optimal` — norm-optimal ILC in its Riccati form (O(N) per update);
* :mod:`host.learning.identification` — the dynamic parameters estimated from measured trials;
* :mod:`host.learning.check` — the convergence check run before an experiment (matrix-free);
* :mod:`host.learning.laws` — every project law, one home: the eight classic laws, ``cno-ilc``,
  ``adjoint-ilc``, the static table ``PROJECT_LAWS``, and ``build_law`` with the one checked wrapper
  every law runs in;
* :mod:`host.learning.protocol` — the public protocol of a law (what it receives after each trial,
  what it returns, its optional iteration map and auxiliary trials), re-exported by ``ilcrig``;
* :mod:`host.learning.registry` — law names: the project's (never shadowed), plug-ins (entry points
  ``ilcrig.laws``, third parties only), ``module:Class``, classes registered in the process, and
  where each came from (import-light);
* :mod:`host.learning.metrics` — the trial metrics and the trace digest.

May import: ``bus``, ``plant`` and :mod:`host.planning`.  Never the nodes, the experiment, the rig or
the public API ``ilcrig``.
No dense lifted (NJ × NJ) matrix is formed anywhere in this package.
"""

"""host.learning: the iterative learning laws.

Owns the law names (:mod:`host.learning.names`), the gains and their normalisation, the laws and
their registry, the lifted model and the convergence check run before an experiment
(:mod:`host.learning.ilc`), and the trial metrics and trace digest (:mod:`host.learning.metrics`).

May import: ``bus``, ``plant`` and :mod:`host.planning`.  Never the nodes, the experiment or the rig.
"""

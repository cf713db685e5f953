"""host.studies.paper: the paper's study — ``ilcrig reproduce`` (docs/usage.md), a predefined sweep
on the engine of :mod:`host.studies`.

Owns its plan (:mod:`host.studies.paper.plan`: which configuration stands behind which row of the
paper's tables and figures, and the beyond-the-paper experiments), the run
(:mod:`host.studies.paper.reproduce`), the published numbers (:mod:`host.studies.paper.paper_data`),
the verdict rules (:mod:`host.studies.paper.verdicts` on the errors after learning,
:mod:`host.studies.paper.convergence_verdicts` on RMSE histories), the claims judged on a sweep
folder (:mod:`host.studies.paper.claims`), and the report (:mod:`host.studies.paper.report`, with its
sections :mod:`host.studies.paper.report_sections`, :mod:`host.studies.paper.report_beyond`, the
torque-limit section :mod:`host.studies.paper.torque_limit` and the figures
:mod:`host.studies.paper.figures`).

May import: ``bus``, ``plant``, :mod:`host.planning`, :mod:`host.learning`, :mod:`host.experiment`,
:mod:`host.analysis` and :mod:`host.studies` (the engine, the point folders, the settling
definitions).  Never the rig, never ``ilcrig``.
"""

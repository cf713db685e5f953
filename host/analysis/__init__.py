"""host.analysis: what a user reads after a run.

Owns the Rerun recording (:mod:`host.analysis.recording`), a run's outputs around the trial loop
(:mod:`host.analysis.session`), the run report (:mod:`host.analysis.run_report`), the paper's
data (:mod:`host.analysis.paper_data`), the ``ilcrig reproduce`` sweep: its plan
(:mod:`host.analysis.sweep_plan`), runner (:mod:`host.analysis.sweep`) and report with verdicts
and figures (:mod:`host.analysis.report`), whose torque-limit section is
:mod:`host.analysis.torque_limit`.

May import: ``bus``, ``plant``, :mod:`host.planning`, :mod:`host.learning`,
:mod:`host.experiment`.  Never the rig.
"""

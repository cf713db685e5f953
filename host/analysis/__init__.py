"""host.analysis: what a user reads after a run.

Owns the Rerun recording (:mod:`host.analysis.recording`: the recorder; the file on disk,
:mod:`host.analysis.recording_segments`; its layout, :mod:`host.analysis.recording_layout`; what it
shows, :mod:`host.analysis.recording_scene`), ``ilcrig view`` (:mod:`host.analysis.viewer`), the live view of ``--view``
(:mod:`host.analysis.live_view`: the Rerun stream on loopback, the robot's live stream), a run's outputs around the trial loop
(:mod:`host.analysis.session`), the run report (:mod:`host.analysis.run_report`), the paper's
data (:mod:`host.analysis.paper_data`), and the ``ilcrig reproduce`` sweep (run by the sweep
engine, :mod:`ilcrig.sweep`): its plan (:mod:`host.analysis.sweep_plan`), the definitions on RMSE
histories (:mod:`host.analysis.settling`: settle iteration, floor, growth), the verdict rules
(:mod:`host.analysis.verdicts` on the errors after learning, :mod:`host.analysis.convergence_verdicts`
on RMSE histories), the claims judged on a sweep folder (:mod:`host.analysis.claims`), the figures
(:mod:`host.analysis.figures`), markdown formatting (:mod:`host.analysis.markdown`) and the report
(:mod:`host.analysis.report`, with its sections :mod:`host.analysis.report_sections`,
:mod:`host.analysis.report_beyond` and the torque-limit section :mod:`host.analysis.torque_limit`).

May import: ``bus``, ``plant``, :mod:`host.planning`, :mod:`host.learning`,
:mod:`host.experiment`.  Never the rig.
"""

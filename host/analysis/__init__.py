"""host.analysis: what a user reads after a run.

Owns the Rerun recording (:mod:`host.analysis.recording`: the recorder; the file on disk,
:mod:`host.analysis.recording_segments`; its layout, :mod:`host.analysis.recording_layout`; what it
shows, :mod:`host.analysis.recording_scene`), ``ilcrig view`` (:mod:`host.analysis.viewer`), the live
view of ``--view`` (:mod:`host.analysis.live_view`: the Rerun stream on loopback, the robot's live
stream), a run's outputs around the trial loop (:mod:`host.analysis.session`), the run report
(:mod:`host.analysis.run_report`), the figure canvas (:mod:`host.analysis.figures`) and markdown
formatting (:mod:`host.analysis.markdown`) it and the studies' reports use.  The studies of many
runs (sweeps, tuning, the paper's reproduction) are :mod:`host.studies`.

May import: ``bus``, ``plant``, :mod:`host.planning`, :mod:`host.learning`,
:mod:`host.experiment`.  Never the rig.
"""

"""host.experiment: one ILC experiment, whatever runs it.

Owns the configuration (:mod:`host.experiment.config`), the plan decided before anything moves
(:mod:`host.experiment.plan`), the trial loop (:mod:`host.experiment.trial_loop`; its state
:mod:`host.experiment.loop_state`, fault placement :mod:`host.experiment.fault_placement`, signals
:mod:`host.experiment.signal_shield`, the pdo transport's TPDO check :mod:`host.experiment.tpdo_check`),
the bench protocol (:mod:`host.experiment.bench`), ``summary.json`` (:mod:`host.experiment.summary`), every trial's
signals as numpy files in the run folder (:mod:`host.experiment.arrays`), fault records and the fault line
(:mod:`host.experiment.faults`), the run folder with its space reserve (:mod:`host.experiment.outputs`), the console
lines, experiment options and exit codes (:mod:`host.experiment.console`) and the in-process
composition root of ``ilcrig sim`` (:mod:`host.experiment.inprocess`).

May import: ``bus``, ``plant``, :mod:`host.planning`, :mod:`host.learning`, :mod:`host.nodes`;
``firmware_model`` only in :mod:`host.experiment.inprocess`.  Never the rig or the analysis.
"""

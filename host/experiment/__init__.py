"""host.experiment: one ILC experiment, whatever runs it.

Owns the configuration (:mod:`host.experiment.config`), the plan decided before anything moves
(:mod:`host.experiment.plan`), the trial loop (:mod:`host.experiment.trial_loop`; its state
:mod:`host.experiment.loop_state`, fault placement :mod:`host.experiment.fault_placement`, signals
:mod:`host.experiment.signal_shield`, the pdo transport's TPDO check :mod:`host.experiment.tpdo_check`, the law's
code watched on the rig :mod:`host.experiment.law_watch`),
the bench protocol (:mod:`host.experiment.bench`), ``summary.json`` (:mod:`host.experiment.summary`), every trial's
signals as numpy files in the run folder (:mod:`host.experiment.arrays`), fault records and the fault line
(:mod:`host.experiment.faults`), the run folder with its space reserve (:mod:`host.experiment.outputs`), the console
lines, the experiment options as data and the plan's refusals as bad input
(:mod:`host.experiment.console`).  The in-process bench is :mod:`host.sim`'s.

May import: ``bus``, ``plant``, :mod:`host.planning`, :mod:`host.learning`, :mod:`host.nodes`.
Never ``firmware_model``, the rig or the analysis.
"""

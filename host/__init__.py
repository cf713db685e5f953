"""host: the host PC of the rig — planning, learning, the experiment, the rig, analysis, the CLI.

Owns, by subpackage: :mod:`host.planning` (paths and trajectories), :mod:`host.learning` (gains,
laws, convergence checks, metrics), :mod:`host.nodes` (the clients of the drives and the bench
node over an object-access protocol), :mod:`host.experiment` (configuration, plan, trial loop,
summary, console, the in-process composition of ``ilcrig sim``), :mod:`host.analysis`
(recording, the run report), :mod:`host.studies` (sweeps, tuning, the paper's ``reproduce``
study on Dask), :mod:`host.rig` (the host role on the bus and the launcher of ``ilcrig run``);
:mod:`host.cli` only parses and dispatches.

May import: ``bus`` and ``plant`` (the nominal model and kinematics).  Never ``firmware_model``,
except :mod:`host.experiment.inprocess` (composition root of ``ilcrig sim``) and :mod:`host.cli`
(``ilcrig drive`` hands its process to the firmware).  Direction inside: planning → learning →
nodes → experiment → analysis → rig / studies → cli (tests/test_architecture.py).
"""

"""host: the host PC of the rig — planning, learning, the experiment, the rig, analysis, the CLI.

Owns, by subpackage: :mod:`host.planning` (paths and trajectories), :mod:`host.learning` (gains,
laws, convergence checks, metrics), :mod:`host.nodes` (the clients of the drives and the bench
node over an object-access protocol), :mod:`host.experiment` (configuration, plan, trial loop,
summary, console), :mod:`host.analysis` (recording, run outputs, the run report),
:mod:`host.studies` (sweeps, tuning, the paper's ``reproduce`` study on Dask), :mod:`host.sim` (the
in-process experiment of ``ilcrig sim`` and the API: a composition root), :mod:`host.rig` (the host
role on the bus and the launchers of ``ilcrig run`` and ``ilcrig robot``); :mod:`host.cli` parses the
command line and hands typed options to the commands.

May import: ``bus`` and ``plant`` (the nominal model and kinematics).  Never ``firmware_model``,
except the two composition roots :mod:`host.sim` (the in-process experiment) and :mod:`host.cli`
(``ilcrig drive`` hands its process to the firmware).  Never the public API ``ilcrig``.
Direction inside: planning → learning → nodes → experiment → analysis → sim, rig, studies → cli
(tests/test_architecture.py).
"""

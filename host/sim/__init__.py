"""host.sim: the in-process experiment — four firmware drives and the true plant in one process.

Owns the composition root of ``ilcrig sim`` and of the public API's in-process runs
(:class:`ilcrig.Experiment`, :class:`ilcrig.Session`): the in-process bench
(:mod:`host.sim.inprocess`) and the trial-by-trial session with the run's outputs
(:mod:`host.sim.session`).  The run outputs (run folder, recording, arrays, ``report.md``) are the
ones of every run, :mod:`host.analysis.session`.

The drives' firmware of a run (``--firmware``) is checked with :func:`check_firmware`
(:func:`firmware_model.firmware_select.check_firmware`, re-exported here, import-light, for the
public API, which reaches the firmware only through this unit).

May import: ``bus``, ``plant``, ``firmware_model`` (the unit is a composition root),
:mod:`host.planning`, :mod:`host.learning`, :mod:`host.nodes`, :mod:`host.experiment`,
:mod:`host.analysis`.  Never the rig, the CLI or the public API ``ilcrig``.
"""

from firmware_model.firmware_select import FIRMWARES, check_firmware

__all__ = ["FIRMWARES", "check_firmware"]

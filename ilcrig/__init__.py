"""ilcrig: the public Python API — experiments in-process or on the rig, trial by trial, results as
numpy arrays, and learning laws from outside the package.

Owns the facade over the internals (which stay where they are: ``host/``, ``plant/``,
``firmware_model/``, ``bus/``), one module per concern:

* :mod:`ilcrig.errors` — :class:`InputError` (bad input, the command line's one-line message),
  :class:`RigError`; :class:`ClusterLost` (a sweep's Dask cluster gone, from :mod:`host.studies.engine`,
  importable without Dask);
* :mod:`ilcrig.experiment` — :class:`Experiment` (from keyword arguments or a TOML file: the keys of
  the command line), :class:`Session` (in-process, one trial per step, gains changeable between
  trials), :func:`available_laws`, :func:`register_law`;
* :mod:`ilcrig.results` — :class:`TrialResult` and :class:`Results` (arrays with units in their
  names, metrics as arrays and as a table, the recording and figures on request), :func:`load`
  (a run folder of ``ilcrig sim`` or ``ilcrig run``);
* :mod:`ilcrig.rig` — :class:`RigRun`, running on the rig: the multi-process ``ilcrig run`` launcher in a child
  process, its trials read from the run folder as they complete;
* :mod:`ilcrig.sweep` — sweeps, Monte Carlo studies and gain tuning of experiments on Dask
  distributed (``ilcrig sweep``, ``ilcrig tune``, ``ilcrig reproduce``; imported on its own:
  ``import ilcrig.sweep``, docs/sweeps.md).

The learning-law protocol (:class:`LearningLaw`, :class:`TrialData`, :class:`LawContext`,
:class:`IterationMap`, :class:`ClosedLoopModel`) is re-exported here from :mod:`host.learning`
(every law of the project lives in :mod:`host.learning.laws`; this package holds none);
:mod:`ilcrig.signals` re-exports the time operators (lead, difference, Q filter, transposes).
docs/api.md explains it with runnable examples.

May import: ``host`` (every subpackage), ``plant``, ``bus``, and ``firmware_model`` only through
:mod:`host.sim` (the in-process experiment this API wraps).  Nothing in ``firmware_model``, ``bus``,
``host`` or ``plant`` imports ``ilcrig``.
"""

from __future__ import annotations

from host.learning.check import ConvergenceReport, IterationMap
from host.learning.laws.base import LawContext
from host.learning.model import ClosedLoopModel
from host.learning.protocol import AUXILIARY, LEARNING, TrialData
from host.learning.protocol import LawProtocol as LearningLaw
from host.learning.registry import ENTRY_POINT_GROUP
from host.studies.engine import ClusterLost
from ilcrig import signals
from ilcrig.errors import InputError, RigError
from ilcrig.experiment import Experiment, Session, available_laws, register_law
from ilcrig.results import Results, TrialResult, load
from ilcrig.rig import RigRun

__all__ = [
    "AUXILIARY",
    "ClosedLoopModel",
    "ClusterLost",
    "ConvergenceReport",
    "ENTRY_POINT_GROUP",
    "Experiment",
    "InputError",
    "IterationMap",
    "LEARNING",
    "LawContext",
    "LearningLaw",
    "Results",
    "RigError",
    "RigRun",
    "Session",
    "TrialData",
    "TrialResult",
    "available_laws",
    "load",
    "register_law",
    "signals",
]

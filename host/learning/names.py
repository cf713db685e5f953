"""The names of the learning laws and gain presets, the default law and the largest number of
trials: what the command line, the configuration and the law registry
(:data:`host.learning.laws.table.PROJECT_LAWS`, :mod:`host.learning.registry`) share.  Import-light on
purpose: every role parses the command line, and the laws themselves pull in scipy and numba.

This module owns the names only; it imports nothing of the project."""

from __future__ import annotations

#: the eight classic built-in laws (:mod:`host.learning.laws.pd`, :mod:`host.learning.laws.norm_optimal`,
#: on :class:`host.learning.laws.base.BuiltinLaw`; the memory model of the preflight is measured for each)
LAWS: tuple[str, ...] = ("pd-ilc", "pd-ilc-q", "pd-ol", "p-ol", "d-ilc", "q-ilc", "no-ilc", "no-ilc-id")
#: the project's laws beyond the classic ones, written on the public protocol directly
#: (:mod:`host.learning.laws.constrained`, :mod:`host.learning.laws.adjoint`)
MORE_LAWS: tuple[str, ...] = ("cno-ilc", "adjoint-ilc")
#: every project law: the names of :data:`host.learning.laws.table.PROJECT_LAWS` (checked at its
#: import), which no plug-in and no registered class may take
PROJECT_LAW_NAMES: tuple[str, ...] = LAWS + MORE_LAWS
#: the law of the default experiment: norm-optimal ILC on the model estimated from the first trial,
#: bounded over long runs and settled by the third trial (the paper's literal ``pd-ilc`` diverges
#: after about a dozen trials; its robust form is ``pd-ilc-q``)
DEFAULT_LAW: str = "no-ilc-id"
#: gain presets, see :data:`host.learning.gains.GAIN_PRESETS`
GAIN_PRESET_NAMES: tuple[str, ...] = ("normalized", "paper")
#: the largest number of trials of one experiment.  A run keeps every trial's error and
#: feed-forward ((N, 4) float64 each) for its summary, report and recording, so memory grows as
#: trials × ticks: 1000 trials of the default 501-tick trial take 32 MB, of a 20 s (20,001-tick)
#: trial 1.3 GB (the preflight's memory model counts it: ``host.experiment.plan.TRIAL_SAMPLE_BYTES``).
#: The convergence check's cost does not depend on it.
MAX_ITERATIONS: int = 1000

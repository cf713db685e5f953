"""Experiments from Python: build one from keyword arguments or a TOML file, run it in-process or on
the rig, or step it trial by trial.

This module owns :class:`Experiment`, :class:`Session` (the in-process trial-by-trial run),
:func:`available_laws` and :func:`register_law`.  The configuration keys are the TOML keys of the
command line (``law``, ``iterations``, ``path``, ``cycle_s``, ``profile``, ``disturbance``, ``seed``,
``ts_s``, ``substeps``, ``ff0``, ``following_error_deg``, ``ff_transport``, ``fieldbus_bitrate``,
``force_bus_fit``, ``gains`` = a dict of ``[gains]`` keys, ``law_options`` = a dict), with the same
validation and the same one-line messages (:class:`ilcrig.InputError`); ``firmware`` (the drives'
control period, ``--firmware``: ``python``, ``c``, ``pil``) is not a configuration key -- it does
not change the experiment -- and goes with the experiment to its in-process and rig runs.  A thin wrapper over host
code: the configuration is :func:`host.experiment.config.build_config`'s, the plan
:func:`host.experiment.console.prepared`'s, and an in-process run is
:class:`host.sim.session.SimSession` — the run of ``ilcrig sim``, so their digests are the CLI's.
"""

from __future__ import annotations

import dataclasses
import difflib
import logging
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TextIO

from host.experiment.config import ExperimentConfig, build_config, gains_table
from host.experiment.console import prepared
from host.experiment.loop_state import TrialOutcome
from host.experiment.plan import Plan
from host.experiment.signal_shield import Interrupted, interrupt_on_signals
from host.learning.check import ConvergenceReport
from host.learning.registry import law_descriptions
from host.learning.registry import register_law as _register
from ilcrig.errors import InputError, input_error
from ilcrig.results import Results, TrialResult

logger = logging.getLogger(__name__)

__all__ = ["Experiment", "Session", "available_laws", "register_law"]


def available_laws() -> dict[str, str]:
    """Every law this process can run by name → its one-line description (the project's laws, plug-ins
    of the entry-point group ``ilcrig.laws``, and classes registered here).

    :raises InputError: a conflicting installation (a plug-in that claims a project law's name, or
        two distributions that claim one name), naming the distribution(s)."""
    return law_descriptions()


def register_law(cls: type[Any], name: str | None = None) -> str:
    """Make the law class ``cls`` usable by ``name`` in this process (in-process runs only; on the
    rig a law must be importable by the host process: a plug-in, or ``module:Class``).

    :raises InputError: the name of a project law (``ilcrig laws`` lists them; none can be replaced),
        or not a law class.
    """
    try:
        return _register(cls, name)
    except ValueError as exc:
        raise input_error(exc) from None


def _law_name(law: Any) -> str:
    """A law given as a class: ``module:Class`` when importable by that name (then the rig's host
    process can import it too), else registered in this process; a law instance (an object with
    ``update``): registered in this process (in-process runs only), built as that very object."""
    if isinstance(law, str):
        return law
    if not isinstance(law, type):
        if not callable(getattr(law, "update", None)):
            raise InputError(
                f"law: a name, a law class or a law instance (with update(trial)), got {type(law).__name__} {law!r:.60}"
            )
        return register_law(_instance_class(law))
    module, qual = law.__module__, law.__qualname__
    found: Any = sys.modules.get(module)
    for part in qual.split("."):
        found = getattr(found, part, None)
    if module != "__main__" and found is law:
        return f"{module}:{qual}"
    return register_law(law)


def _instance_class(law: Any) -> type[Any]:
    """A law class whose construction gives the instance ``law`` (the context is not passed to it:
    the instance was built by the caller), named as the instance (its ``name``, else its class's)."""
    own = getattr(law, "name", None)
    name = own if isinstance(own, str) and own.strip() else type(law).__name__

    def new(cls: type[Any], ctx: Any) -> Any:
        return law

    attrs = {
        "__new__": new,
        "name": name,
        "description": getattr(law, "description", None) or f"a {type(law).__name__} instance given to the API",
        "update": lambda self, trial: law.update(trial),
        #: marks the class of an instance (:class:`ilcrig.RigRun` refuses it: in-process runs only)
        "law_instance": True,
        "__module__": __name__,
    }
    return type(f"Instance{type(law).__name__}", (), attrs)


def _suggest(unknown: dict[str, Any]) -> InputError:
    """The one-line error of unknown keys, each with the closest known key when there is one."""
    parts = []
    for key in sorted(unknown):
        close = difflib.get_close_matches(key, KEYS, n=1)
        parts.append(f"{key!r} (did you mean {close[0]}?)" if close else repr(key))
    noun = "key" if len(parts) == 1 else "keys"
    return InputError(f"unknown {noun} {', '.join(parts)}; the keys: {', '.join(KEYS)}")


#: the configuration keys (the TOML file's and the command line's), in :class:`Experiment`'s order
KEYS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(ExperimentConfig))


class Experiment:
    """One experiment (module docstring).

    ``Experiment(law="pd-ilc", iterations=5)`` or ``Experiment("exp.toml", cycle_s=0.15)``: keyword
    arguments override the file's keys (``gains`` and ``law_options`` merge key by key), as command
    line options do; a key left at None takes the file's value, else the command line's default
    (in brackets below).

    :param config: a TOML file of the keys (``ilcrig sim --config``)
    :param law: a law's name [``no-ilc-id``], a law class (``module:Class`` when importable by that
        name, else registered in this process) or a law instance (in-process runs only)
    :param iterations: trials to run [10]
    :param path: a built-in path 1–4 or a path file [``1``]
    :param cycle_s: the pick-and-place cycle, s [0.25]
    :param profile: ``ruckig`` or a motion law (``poly4567``, ``poly5``) [``ruckig``]
    :param disturbance: ``none``, ``repetitive``, ``nonrepetitive`` … [``none``]
    :param seed: the random seed of the disturbance [0]
    :param ts_s: the sample time, s [0.001]
    :param substeps: RK4 sub-steps per tick [4]
    :param ff0: the first trial's feed-forward (``model``, ``zero``) [``model``]
    :param following_error_deg: the drives' following-error limit, deg [10]
    :param ff_transport: ``table`` (SDO) or ``pdo`` (CSP set-points) [``table``]
    :param fieldbus_bitrate: the fieldbus bit rate, bit/s [1000000]
    :param force_bus_fit: run even when the cyclic frames do not fit the bus [False]
    :param gains: ``[gains]`` keys (``preset``, ``alpha``, ``beta``, ``lp``, ``ld``, …)
    :param law_options: the law's own options
    :param plant: plant uncertainty factors (``inertia_scale``, ``mass_scale``, …)
    :param firmware: the drives' control period, ``python`` (the reference model), ``c`` (the C core,
        software in the loop) or ``pil`` (``--firmware``, docs/firmware.md) [``python``]
    :param unknown: no other key: refused with the closest known key as a hint
    :raises InputError: a bad key or value (the command line's one-line message).
    """

    def __init__(
        self,
        config: str | Path | None = None,
        /,
        *,
        law: str | type[Any] | object | None = None,
        iterations: int | None = None,
        path: str | int | Path | None = None,
        cycle_s: float | None = None,
        profile: str | None = None,
        disturbance: str | None = None,
        seed: int | None = None,
        ts_s: float | None = None,
        substeps: int | None = None,
        ff0: str | None = None,
        following_error_deg: float | None = None,
        ff_transport: str | None = None,
        fieldbus_bitrate: int | None = None,
        force_bus_fit: bool | None = None,
        gains: dict[str, Any] | None = None,
        law_options: dict[str, Any] | None = None,
        plant: dict[str, Any] | None = None,
        firmware: str | None = None,
        **unknown: Any,
    ) -> None:
        from host.sim import check_firmware

        if unknown:
            raise _suggest(unknown)
        #: the drives' firmware (``--firmware``), checked now: before anything starts
        self.firmware: str = check_firmware(firmware if firmware is not None else "python")
        given = {
            "law": law,
            "iterations": iterations,
            "path": path,
            "cycle_s": cycle_s,
            "profile": profile,
            "disturbance": disturbance,
            "seed": seed,
            "ts_s": ts_s,
            "substeps": substeps,
            "ff0": ff0,
            "following_error_deg": following_error_deg,
            "ff_transport": ff_transport,
            "fieldbus_bitrate": fieldbus_bitrate,
            "force_bus_fit": force_bus_fit,
            "gains": gains,
            "law_options": law_options,
            "plant": plant,
        }
        keys = {k: v for k, v in given.items() if v is not None}
        if "law" in keys:
            keys["law"] = _law_name(keys["law"])
        try:
            self.config: ExperimentConfig = build_config(config, keys)
        except (ValueError, FileNotFoundError) as exc:
            raise input_error(exc) from None
        self._plan: Plan | None = None

    @classmethod
    def from_toml(cls, path: str | Path, **keys: Any) -> Experiment:
        """The experiment of a TOML file (keys as the command line's), ``keys`` overriding it."""
        return cls(path, **keys)

    @classmethod
    def from_config(cls, config: ExperimentConfig) -> Experiment:
        """An experiment of an already validated configuration."""
        exp = cls.__new__(cls)
        exp.config, exp._plan, exp.firmware = config, None, "python"
        return exp

    def __repr__(self) -> str:
        c = self.config
        return f"Experiment(law={c.law!r}, iterations={c.iterations}, path={c.path!r}, cycle_s={c.cycle_s})"

    def replace(self, **keys: Any) -> Experiment:
        """A copy with ``keys`` changed (validated like the constructor's)."""
        base = {k: v for k, v in self.config.as_dict().items() if k != "gains"}
        base["gains"] = gains_table(self.config.gains) | dict(keys.pop("gains", None) or {})
        return Experiment(**({"firmware": self.firmware} | base | keys))

    @property
    def plan(self) -> Plan:
        """Everything decided before anything moves (trajectory, gains, law, convergence check),
        computed once.

        :raises InputError: an infeasible experiment (the command line's one-line message)."""
        if self._plan is None:
            self._plan = prepared(self.config)
        return self._plan

    @property
    def check(self) -> ConvergenceReport:
        """The convergence check before the run (``checked`` False for a law without a map)."""
        return self.plan.check

    @property
    def n_ticks(self) -> int:
        """N, the samples per trial."""
        return self.plan.n_ticks

    # -- running ---------------------------------------------------------------------------------

    def start(self, out: str | Path | None = None, *, stream: TextIO | None = None, view: bool = False) -> Session:
        """An in-process run, one trial per :meth:`Session.step` (``out``: a run folder with the
        outputs of ``ilcrig sim``; ``stream``: the console lines; ``view``: stream the recording
        live to a Rerun viewer, ``--view``, see :attr:`Session.live_url`)."""
        return Session(self, out, stream=stream, view=view)

    def run(
        self,
        mode: str = "sim",
        out: str | Path | None = None,
        *,
        stream: TextIO | None = None,
        **rig: Any,
    ) -> Results:
        """Run every trial and return the results.

        :param mode: ``sim`` (in this process) or ``rig`` (the multi-process ``ilcrig run`` launcher,
            :mod:`ilcrig.rig`; ``rig`` options: ``bus``, ``hub``, ``realtime``, ``bus_time``,
            ``io_bitrate``, ``timeout_s``)
        :param out: the run folder (sim: optional, nothing is written without it; rig: default
            ``runs/api-rig-<time>``)
        :param stream: the console lines (plan, one row per trial); none by default
        :raises InputError: bad input (before anything moves)
        """
        if mode == "sim":
            if rig:
                raise InputError(f"{', '.join(sorted(rig))}: options of the rig; mode 'sim' takes none")
            with self.start(out, stream=stream) as session:
                for _ in session:
                    pass
            return session.results
        if mode == "rig":
            from ilcrig.rig import RigRun

            with RigRun(self.config, out, stream=stream, firmware=self.firmware, **rig) as run:
                for _ in run:
                    pass
            return run.results
        raise InputError(f"mode must be 'sim' or 'rig', got {mode!r}")

    def trials(self, mode: str = "sim", out: str | Path | None = None, **rig: Any) -> Iterator[TrialResult]:
        """Each trial's result as it completes (``mode`` and options as :meth:`run`).  Leaving the
        loop early ends the run (the rig: interrupted, its completed trials kept)."""
        if mode == "sim":
            if rig:
                raise InputError(f"{', '.join(sorted(rig))}: options of the rig; mode 'sim' takes none")
            with self.start(out) as session:
                yield from session
            return
        if mode == "rig":
            from ilcrig.rig import RigRun

            with RigRun(self.config, out, firmware=self.firmware, **rig) as run:
                yield from run
            return
        raise InputError(f"mode must be 'sim' or 'rig', got {mode!r}")


class Session:
    """An in-process run of an :class:`Experiment`, one trial per :meth:`step` (also an iterator and
    a context manager: leaving it ends the run with the bench's safe state and the final summary).

    Between trials :meth:`set_gains` changes the gains: the drives get the new feedback gains, the law
    is built again for them and continues from the current feed-forward.  The run itself is
    :class:`host.sim.session.SimSession` (as ``ilcrig sim``'s); this class gives its trials as
    :class:`TrialResult`.
    """

    def __init__(
        self, experiment: Experiment, out: str | Path | None = None, *, stream: TextIO | None = None, view: bool = False
    ) -> None:
        from host.sim.session import SimSession

        self.experiment = experiment
        plan = experiment.plan
        self._sim = SimSession(plan, out, stream=stream, view=view, firmware=experiment.firmware)
        self.out = self._sim.out
        self.stream = stream
        #: the live stream's address (``rerun+http://127.0.0.1:PORT/proxy``) with ``view``, else None
        self.live_url: str | None = self._sim.live_url
        self.trials: list[TrialResult] = []
        self._reference = {"t_s": plan.ref.t, "q_rad": plan.ref.q}
        #: the run's interrupt was raised to the caller already
        self._raised = False

    def __enter__(self) -> Session:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> None:
        if exc is not None and not self._raised and not isinstance(exc, GeneratorExit):  # GeneratorExit: a
            # loop over ``Experiment.trials()`` left early, the run is stopped, as by ``close()``
            # the caller's own code failed (or was interrupted) inside the ``with`` block: the
            # run ends with every kept trial and the summary says why; the exception goes on
            self._sim.end_by_user(exc)
        self.close()

    def __iter__(self) -> Iterator[TrialResult]:
        while (t := self.step()) is not None:
            yield t

    @property
    def plan(self) -> Plan:
        """The plan in force (its gains change with :meth:`set_gains`)."""
        return self._sim.plan

    @property
    def done(self) -> bool:
        return self._sim.done

    def step(self) -> TrialResult | None:
        """Run the next trial (a learning trial, or an auxiliary rollout its law asked for); None
        when the run is over (every trial ran, or a fault ended it: see :attr:`results`).

        A trial is kept before the law learns from it: when the law's update fails, the trial is
        still returned (and in :attr:`results`), the run has ended (``end_reason`` ``law_error``)
        and the next step returns None.  SIGINT / SIGTERM (Ctrl-C) during a step end the run
        through its fault path and are then raised here as :class:`KeyboardInterrupt` (the
        completed trials in :attr:`results`, the run folder and ``summary.json`` alike).
        """
        with interrupt_on_signals():  # SIGINT / SIGTERM during the step: through the run's fault path
            try:
                outcome = self._sim.step()
            except KeyboardInterrupt as exc:  # raised outside the trial loop's guard: end the run here
                self._sim.end_by_user(exc)
                outcome = None
        if outcome is not None:
            self.trials.append(self._result(outcome))  # kept: in every view of the run
        interrupted = self._sim.result.interrupted
        if interrupted is not None and not self._raised:
            # the run ended by an interrupt (also one during the law's update): its trials are in
            # every view now; the interrupt goes on to the caller, never swallowed
            self._raised = True
            raise Interrupted(interrupted)
        return self.trials[-1] if outcome is not None else None

    def _result(self, o: TrialOutcome) -> TrialResult:
        channels = {
            "position_counts": [tr.position_counts for tr in o.traces],
            "torque_units": [tr.torque_units for tr in o.traces],
            "torque_fb_units": [tr.torque_fb_units for tr in o.traces],
        }
        arrays: dict[str, Any] = {k: _stack_columns(v) for k, v in channels.items()}
        arrays["feedforward_nm"] = o.feedforward_nm
        return TrialResult.from_recorder(o.k, o.role, self._reference, arrays, o.metrics.as_dict(), o.gains.as_dict())

    def set_gains(self, **changes: Any) -> None:
        """Change the gains before the next trial: ``[gains]`` keys (``alpha``, ``beta``, ``lp``,
        ``ld``, ``lp_norm``, ``ld_norm``, ``lead``, ``q_cutoff_hz``, …, ``preset``).

        :raises InputError: a bad key or value (the configuration's message), a feedback gain outside
            the drive's range, or a change between a learning trial and its auxiliary trials.
        """
        self._sim.set_gains(**changes)

    @property
    def results(self) -> Results:
        """The results so far (all of them after the run)."""
        return Results(self._sim.result.summary, self.trials, self.out)

    def close(self) -> Results:
        """End the run (bench closed, final summary; with a run folder also ``report.md``)."""
        self._sim.close()
        return self.results

    @property
    def raw(self) -> Any:
        """The trial loop's own result (:class:`host.experiment.loop_state.ExperimentResult`)."""
        return self._sim.result


def _stack_columns(columns: list[Any]) -> Any:
    import numpy as np

    return np.stack([np.asarray(c) for c in columns], axis=1)

"""Running an experiment on the rig: the multi-process ``ilcrig run`` launcher in a child process,
its trials read from the run folder as they complete.

This module owns :class:`RigRun`.  The experiment is checked in this process first (the same
preparation the launcher's preflight makes, so bad input is an :class:`ilcrig.InputError` with the
command line's message before anything starts), written to ``<out>/experiment.toml`` and run as
``python -m host.cli run --config <out>/experiment.toml --out <out> --bus …`` (started by
:func:`bus.processes.spawn_process`: its own session, and SIGTERM — the launcher's interrupt path —
when the thread that created the :class:`RigRun` ends, so a killed caller leaves no rig running) with
this interpreter and this process's ``sys.path`` on ``PYTHONPATH`` (so a law importable here —
a plug-in, or ``module:Class`` — is importable by the rig's host process too).  The launcher's
console output goes to ``<out>/console.txt`` (and to ``stream``).

Trials as they complete: the host role rewrites ``summary.json`` after every trial, after the
trial's arrays (``trials/``, :mod:`host.experiment.arrays`) are written; each trial listed there is
read back as a :class:`ilcrig.TrialResult`.  Leaving early (``stop()``, a ``break`` out of the
iteration, Ctrl-C, an exception of the caller's code in the ``with`` block) sends the launcher SIGINT:
the rig ends through its one fault path (torque off, ``interrupted`` in the summary) and the
completed trials are kept; the caller's own exception is then recorded in the summary as an
in-process session records it (``end_reason`` ``user_exception``).  A law registered only in this
process (:func:`ilcrig.register_law`) cannot run on the rig: it is refused before the start.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TextIO

from bus.exit_codes import EXIT_CHILD_FAILED, EXIT_USAGE
from bus.processes import spawn_process
from host.experiment.arrays import load_reference, load_trial
from host.experiment.config import ExperimentConfig, config_toml
from host.experiment.outputs import SUMMARY_NAME, default_run_folder, read_summary
from host.learning.protocol import LEARNING
from host.learning.registry import law_class, registered_here
from ilcrig.errors import InputError, RigError, input_error
from ilcrig.results import Results, TrialResult, load

logger = logging.getLogger(__name__)

__all__ = ["RigRun", "config_toml"]

#: how often the run folder is looked at while the rig runs, s
POLL_S = 0.05
#: how long the launcher gets to end after SIGINT before it is killed, s
STOP_GRACE_S = 60.0


class RigRun:
    """One experiment on the rig (module docstring); an iterator of its trials and a context manager.

    :param config: the experiment (an :class:`ilcrig.Experiment`, or its validated configuration
        :attr:`ilcrig.Experiment.config`)
    :param out: the run folder (default ``runs/api-rig-<time>``)
    :param stream: where the launcher's console lines go besides ``<out>/console.txt``
    :param bus: the transport (``auto``, ``hub``, ``socketcan``, ``udp_multicast``, ``can_config``)
    :param hub: the hub address (default: a private socket per run)
    :param realtime: pace the plant to the wall clock (``--realtime``)
    :param bus_time: the hub carries the channels in bus time (``--bus-time``)
    :param io_bitrate: the io channel's bit rate for the bus-time figures, bit/s
    :param firmware: the drives' control period (``--firmware``: ``python``, ``c``, ``pil``)
    :param timeout_s: stop the rig (and raise :class:`ilcrig.RigError`) after this long (None: no limit)
    """

    def __init__(
        self,
        config: ExperimentConfig | Any,
        out: str | Path | None = None,
        *,
        stream: TextIO | None = None,
        bus: str = "auto",
        hub: str | None = None,
        realtime: bool = False,
        bus_time: bool = False,
        io_bitrate: int | None = None,
        firmware: str = "python",
        timeout_s: float | None = None,
    ) -> None:
        from host.experiment.outputs import check_out_dir
        from host.experiment.plan import prepare
        from host.sim import check_firmware

        check_firmware(firmware)  # refused with one line before anything starts

        if not isinstance(config, ExperimentConfig):  # an ilcrig.Experiment (not imported: no import circle)
            config = getattr(config, "config", config)
        if not isinstance(config, ExperimentConfig):
            raise InputError(f"RigRun: an ilcrig.Experiment (or its ExperimentConfig), got {type(config).__name__}")
        self.config = config
        law = config.law
        if registered_here(law) and getattr(law_class(law), "law_instance", False):
            raise InputError(
                f"law {law!r} is a law instance, which runs in this process only; on the rig give its class, "
                "importable by module:Class (or installed as a plug-in, entry point group ilcrig.laws)"
            )
        if registered_here(law):
            raise InputError(
                f"law {law!r} is registered in this process only; on the rig the host process must import it: "
                "install it as a plug-in (entry point group ilcrig.laws) or give module:Class"
            )
        try:
            prepare(config, rig=True)  # the launcher's preflight, here: bad input before anything starts
        except (ValueError, FileNotFoundError) as exc:
            raise input_error(exc) from None
        self.out = Path(out) if out is not None else default_run_folder("api-rig", claim=True)
        try:
            check_out_dir(self.out, iterations=config.iterations, n_ticks=config.n_ticks)
        except ValueError as exc:
            raise input_error(exc) from None
        toml_path = self.out / "experiment.toml"
        toml_path.write_text(config_toml(config), encoding="utf-8")
        argv = [sys.executable, "-P", "-m", "host.cli", "run", "--config", str(toml_path), "--out", str(self.out), "--bus", bus]
        if hub is not None:
            argv += ["--hub", hub]
        if realtime:
            argv.append("--realtime")
        if bus_time:
            argv.append("--bus-time")
        if io_bitrate is not None:
            argv += ["--io-bitrate", str(int(io_bitrate))]
        if firmware != "python":
            argv += ["--firmware", firmware]
        env = dict(os.environ)
        # the folder that holds the project's packages first: a plant.py, bus.py or host.py in the
        # user's folders (on this process's sys.path) must not shadow them in the rig's processes
        home = str(Path(__file__).resolve().parent.parent)
        # (the empty entry of ``python -c`` and the REPL is this process's working folder)
        found = [p or os.getcwd() for p in sys.path]
        paths = [home] + [p for p in found if p != home and Path(p).is_dir()]
        env["PYTHONPATH"] = os.pathsep.join(paths + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        self.stream = stream
        self.timeout_s = timeout_s
        self._t0 = time.monotonic()
        self._err_path = self.out / "console.err"
        self._console = open(self.out / "console.txt", "w", encoding="utf-8")  # noqa: SIM115 - closed in close()
        self._err = open(self._err_path, "wb")  # noqa: SIM115 - closed in close()
        # the launcher's lifetime policy (bus.processes): a session of its own, and SIGTERM (its
        # interrupt path: the rig stopped, the summary kept) when the thread that started it ends
        self.proc = spawn_process(argv, stdout=subprocess.PIPE, stderr=self._err, env=env, text=True, death_signal=signal.SIGTERM)
        self._reader = threading.Thread(target=self._pump, name="ilcrig-rig-console", daemon=True)
        self._reader.start()
        self.trials: list[TrialResult] = []
        self._reference: dict[str, Any] | None = None
        self._closed = False
        self._results: Results | None = None
        logger.info("rig started (pid %d): %s", self.proc.pid, " ".join(argv))

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._console.write(line)
            self._console.flush()
            if self.stream is not None:
                self.stream.write(line)
                self.stream.flush()

    def __enter__(self) -> RigRun:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> None:
        if exc is not None and not isinstance(exc, GeneratorExit):
            # the caller's own code failed (or was interrupted) inside the ``with`` block: the rig is
            # stopped now (not run to its end), its completed trials kept, and the summary says why
            self.stop()
            if not isinstance(exc, KeyboardInterrupt):
                self._note_user_exception(exc)
        self.close()

    def _note_user_exception(self, exc: BaseException) -> None:
        """``end_reason`` ``user_exception`` (and ``user_exception``: type, first line, the last kept
        trial) in the stopped rig's summary, as an in-process session records it; a run that had
        completed before the caller's code raised stays completed.  The rig was stopped by SIGINT:
        ``interrupted`` says where."""
        summary = self._summary()
        if summary is None or summary.get("completed"):
            return
        from host.experiment.summary import write_summary

        text = str(exc)
        iterations = summary.get("iterations", [])
        summary["end_reason"] = "user_exception"
        summary["user_exception"] = {
            "type": type(exc).__qualname__,
            "message": text.splitlines()[0] if text else "",
            "after_trial": len(iterations) - 1 if iterations else None,
        }
        try:
            write_summary(self.out, summary)
        except Exception as err:  # noqa: BLE001 - the caller's exception goes on; the rig's summary stays
            logger.warning("the user exception could not be noted in %s: %s", self.out / SUMMARY_NAME, err)

    def _summary(self) -> dict[str, Any] | None:
        return read_summary(self.out)

    def _new_trials(self) -> list[TrialResult]:
        s = self._summary()
        if s is None:
            return []
        its = s.get("iterations", [])
        out = []
        for k in range(len(self.trials), len(its)):
            if self._reference is None:
                self._reference = load_reference(self.out)
            gains = s.get("gains", {})
            t = TrialResult.from_recorder(
                k, its[k].get("role", LEARNING), self._reference, load_trial(self.out, k), its[k], gains
            )
            self.trials.append(t)
            out.append(t)
        return out

    def __iter__(self) -> Iterator[TrialResult]:
        try:
            while True:
                running = self.proc.poll() is None
                yield from self._new_trials()
                if not running:
                    break
                if self.timeout_s is not None and time.monotonic() - self._t0 > self.timeout_s:
                    self.stop()
                    raise RigError(f"the rig did not finish within {self.timeout_s:g} s (stopped); its run folder: {self.out}")
                time.sleep(POLL_S)
        except GeneratorExit:
            self.stop()
            raise
        except KeyboardInterrupt:
            self.stop()
            raise
        self.close()

    def stop(self) -> None:
        """End the run early: SIGINT to the launcher (its fault path: torque off, summary kept)."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(timeout=STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()

    def close(self) -> Results:
        """Wait for the launcher, then the results (:class:`ilcrig.InputError` when the rig refused
        the input, :class:`ilcrig.RigError` when it could not start)."""
        if self._results is not None:
            return self._results
        if not self._closed:
            self._closed = True
            self.proc.wait()
            self._reader.join()
            self._console.close()
            self._err.close()
        code = self.proc.returncode
        err = self._err_path.read_text(encoding="utf-8", errors="replace").splitlines() if self._err_path.is_file() else []
        line = next((ln for ln in reversed(err) if ln.startswith("ilcrig: ")), "")
        if code == EXIT_USAGE:
            raise InputError(line.removeprefix("ilcrig: error: ") or f"the rig refused the experiment (see {self._err_path})")
        if not (self.out / SUMMARY_NAME).is_file():
            raise RigError(f"{line or f'the rig ended with exit code {code}'}; its run folder: {self.out}")
        if code == EXIT_CHILD_FAILED:
            raise RigError(line or f"a role process of the rig could not be started; its run folder: {self.out}")
        self._results = load(self.out)
        self.trials = self._results.trials
        return self._results

    @property
    def results(self) -> Results:
        """The results (after the run: every trial; waits for the launcher)."""
        return self.close()

    @property
    def returncode(self) -> int | None:
        """The launcher's exit code (None while it runs)."""
        return self.proc.poll()

"""``ilcrig host``: the host role of the rig (also what ``ilcrig run`` starts).

This module owns :class:`HostOptions` (the role's typed options) and :func:`run_host_role`, the
composition root of the host process: it prepares
the experiment, opens the fieldbus and builds the ``canopen.Network`` on it, hands the network to
a :class:`host.rig.rig_bench.RigBench`, runs the session (:func:`host.analysis.session.run_session`,
summary mode ``rig``) and prints the run's closing lines (timing, bus time, frame counts, the
trace digest). It disconnects the network at the end, after the bench is closed.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import canopen

from bus.errors import IlcrigError
from bus.exit_codes import EXIT_FAULT
from bus.traffic import DEFAULT_BITRATE
from bus.transports.config import FIELDBUS, IO, TransportConfig
from host.analysis.session import report_fault, run_session
from host.experiment.config import ExperimentConfig
from host.experiment.console import prepared, print_plan
from host.experiment.loop_state import ExperimentResult
from host.experiment.outputs import SUMMARY_NAME
from host.experiment.plan import rehearse_first_update
from host.experiment.signal_shield import interrupt_on_signals
from host.rig.bus_accounting import bus_time_lines
from host.rig.realtime import timing_line
from host.rig.rig_bench import RigBench

logger = logging.getLogger(__name__)

__all__ = ["HostOptions", "run_host_role"]


@dataclass(frozen=True)
class HostOptions:
    """The host role's options beyond the experiment and the transport (``ilcrig host``)."""

    #: the run folder (None: ``runs/rig-<time>``)
    out: Path | None = None
    #: seconds to wait for the nodes to answer
    wait_s: float = 120.0
    #: seconds to pause between trials
    pause_s: float = 0.0
    #: > 0: a node lost between trials is waited for (up to ``wait_s``) and set up again
    recover_s: float = 0.0
    #: the plant paces its ticks to the wall clock (``--realtime``)
    realtime: bool = False
    #: what the launcher's ``--realtime`` got (its scheduling record), None when started alone
    rt_scheduling: dict[str, Any] | None = None
    #: the io channel's bit rate for the bus-time figures, bit/s (None: the default)
    io_bitrate: int | None = None
    #: the hub carries both channels in bus time
    bus_time: bool = False
    #: stream the recording live to a Rerun viewer
    view: bool = False
    #: the launcher's ``--inject diskfull@…`` spec text
    inject_disk_full: str | None = None
    #: the drives' firmware (``--firmware``), recorded in ``summary["bench"]["firmware"]``
    firmware: str = "python"


def run_host_role(opts: HostOptions, cfg: ExperimentConfig, transport: TransportConfig) -> int:
    """``ilcrig host``: run the experiment over the bus; returns the exit code.

    :raises InputError: a bad run folder or an infeasible experiment (before the bus is opened)
    """
    from host.experiment.outputs import check_out_dir, default_run_folder

    named = opts.out if opts.out is not None else default_run_folder("rig", claim=False)
    check_out_dir(named, iterations=cfg.iterations, n_ticks=cfg.n_ticks, create=False)
    plan = prepared(cfg)
    out = opts.out if opts.out is not None else default_run_folder("rig", claim=True)
    check_out_dir(out, iterations=cfg.iterations, n_ticks=plan.n_ticks)
    print_plan(sys.stdout, "host", plan, extra=f", transport {transport.name}")
    # what the law's first update imports or compiles (scipy.signal, numba kernels) is paid now, in
    # this process, while the nodes boot: not after trial 0, under the watch of their heartbeat
    # consumers, and not as a delay of trial 1
    rehearse_first_update(plan.law, plan.u0)
    network = None
    try:
        network = canopen.Network(transport.open(FIELDBUS))
        bench = RigBench(
            cfg,
            network,
            transport,
            out_dir=out,
            wait_s=opts.wait_s,
            pause_s=opts.pause_s,
            recover_s=opts.recover_s,
            realtime=opts.realtime,
            rt_scheduling=opts.rt_scheduling,
            io_bitrate=opts.io_bitrate or DEFAULT_BITRATE,
            fieldbus_bitrate=cfg.fieldbus_bitrate,
            bus_time_hub=opts.bus_time,
            firmware=opts.firmware,
        )
    except (OSError, can.CanError, IlcrigError) as exc:
        _disconnect(network)
        sys.stderr.write(f"ilcrig: error: cannot open the bus ({transport.name}): {exc}\n")
        return EXIT_FAULT
    fail_from, spec = _disk_full_injection(opts.inject_disk_full, cfg.iterations, bench)
    try:
        with interrupt_on_signals():
            res = run_session(
                plan,
                bench,
                out,
                mode="rig",
                stream=sys.stdout,
                fail_writes_from_trial=fail_from,
                fail_spec=spec,
                view=opts.view,
            )
    finally:
        bench.close()  # run_session closed it already, unless it was interrupted before
        _disconnect(network)
    _print_closing_lines(res, out)
    return report_fault(res, out / SUMMARY_NAME)


def _disk_full_injection(text: str | None, iterations: int, bench: RigBench) -> tuple[int | None, str | None]:
    """``--inject diskfull@WHEN`` of the launcher (its spec text): the first trial whose outputs'
    writes fail (−1: from the first summary on) and the spec; ``@T:N`` is the io log in trial T,
    set on the bench's channels here (then no output write fails on purpose)."""
    if not text:
        return None, None
    from bus.transports.fault_inject import WHEN_BEFORE, WHEN_TICK, parse_spec

    spec = parse_spec(text).resolved(iterations)
    if spec.when == WHEN_TICK:
        bench.channels.fail_log_from(spec.trial, spec.tick, spec.text)
        return None, spec.text
    return (-1 if spec.when == WHEN_BEFORE else spec.trial), spec.text


def _disconnect(network: canopen.Network | None) -> None:
    """Release the fieldbus. Never raises."""
    if network is None:
        return
    try:
        network.disconnect()
    except Exception:  # noqa: BLE001 - closing must never hide the original error
        logger.debug("disconnect failed", exc_info=True)


def _print_closing_lines(res: ExperimentResult, out: Path) -> None:
    """Timing, the bus-time hub, bus time, ticks and frames and the trace digest on stdout."""
    s = res.summary
    bench = s.get("bench", {})
    ch = bench.get("channels", {})
    fb = ch.get(FIELDBUS, {})
    timing = bench.get("timing")
    if timing and timing.get("trials"):
        sys.stdout.write(timing_line(timing) + "\n")
    hub_rates = bench.get("bus_time_hub")
    if hub_rates:
        sys.stdout.write(
            f"bus-time hub: io at {hub_rates[IO] / 1000:g} kbit/s, fieldbus at {hub_rates[FIELDBUS] / 1000:g} "
            f"kbit/s: frames delivered in arbitration order, each after its bit time\n"
        )
    bus_time = bench.get("bus_time")
    if bus_time and s["iterations"]:
        sys.stdout.write("".join(line + "\n" for line in bus_time_lines(bus_time)))
    sys.stdout.write(
        f"{s['ticks']} ticks, {s['ticks_per_s']:.0f} ticks/s in trials (host's wall clock); fieldbus {fb.get('frames', 0)} "
        f"frames, io {ch.get(IO, {}).get('frames', 0)} frames; "
        f"trace_sha256 {s['trace_sha256'][:16]}…; summary: {out / SUMMARY_NAME}\n"
    )
    sys.stdout.flush()

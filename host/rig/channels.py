"""The host's passive view of both channels: one :class:`host.rig.monitor.ChannelMonitor` per
channel (fieldbus, io) feeding the bus-time accounting (:class:`host.rig.bus_accounting.BusTimeAccounting`).

This module owns :class:`RigChannels`: it opens the monitors' buses from the run's transport (an
ordinary member of each channel, apart from the canopen network), tells where the io channel's
trial and tick stand, lists what went wrong on a channel for the watchdog
(:class:`host.rig.fault_classify.BusError`, :class:`host.rig.fault_classify.ChannelTrouble`) and
gives the summary's per-channel frame counts.  :meth:`RigChannels.fail_log_from` is the fault
injection of a full disk in a trial (``--inject diskfull@T:N``: the io log fails there).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bus.transports.config import FIELDBUS, HUB_INTERFACE, IO, TransportConfig
from host.rig.bus_accounting import BusTimeAccounting
from host.rig.fault_classify import BusError, ChannelTrouble
from host.rig.monitor import ChannelMonitor

logger = logging.getLogger(__name__)

__all__ = ["RigChannels"]


class RigChannels:
    """The monitors of the fieldbus and the io channel (see the module docstring).

    :param transport: the run's transport; each monitor opens its own passive bus of it
    :param out_dir: the candump logs ``fieldbus.log`` and ``io.log`` go here (None: no logs)
    :param bus_time: takes every frame of both channels
    """

    def __init__(self, transport: TransportConfig, out_dir: Path | None, bus_time: BusTimeAccounting) -> None:
        self.bus_time = bus_time
        self.out_dir = out_dir
        self.monitors: list[ChannelMonitor] = []
        try:
            for name in (FIELDBUS, IO):
                log = (out_dir / f"{name}.log") if out_dir is not None else None
                if log is not None:
                    log.parent.mkdir(parents=True, exist_ok=True)
                classify = bus_time.add_io if name == IO else bus_time.add_fieldbus
                # rounds with pauses only where the hub holds the frames; a kernel socket would drop them
                bulk = transport.channel(name).interface == HUB_INTERFACE
                self.monitors.append(
                    ChannelMonitor(
                        transport.open(name, passive=True),
                        name,
                        log,
                        classify,
                        bulk=bulk,
                        classify_frames=bus_time.add_io_frames if name == IO else None,
                    )
                )
        except BaseException:
            self.close()
            raise

    def fail_log_from(self, trial: int, tick: int, spec: str) -> None:
        """Fault injection: the io channel's log fails with ``ENOSPC`` from tick ``tick`` of trial
        ``trial`` on; the injection is recorded as ``spec`` (``logs/injections-host.jsonl``)."""
        io_mon = self.io
        if io_mon is None:
            return
        log_dir = self.out_dir / "logs" if self.out_dir is not None else None

        def record(at_trial: int, at_tick: int | None) -> None:
            from bus.transports.fault_inject import write_record

            path = log_dir / "injections-host.jsonl" if log_dir is not None and log_dir.is_dir() else None
            write_record(
                path,
                {
                    "by": "host",
                    "spec": spec,
                    "kind": "diskfull",
                    "target": "io.log",
                    "trial": at_trial,
                    "tick": at_tick,
                    "kept": at_trial,
                    "when": "tick",
                },
            )

        io_mon.on_log_fail_injected = record
        io_mon.fail_log_from = (trial, tick)

    @property
    def io(self) -> ChannelMonitor | None:
        """The io channel's monitor (None once closed)."""
        return next((m for m in self.monitors if m.name == IO), None)

    def running_tick(self) -> int | None:
        """The tick of the trial running now on the io channel (None between trials)."""
        io_mon = self.io
        return io_mon.follower.tick if io_mon is not None and io_mon.follower.in_trial else None

    def trial_tick(self, trial: int) -> int | None:
        """The last tick of ``trial`` seen on the io channel, also when the plant has stopped the
        trial already (it does so on a fault it sees); None when the io channel has not shown that
        trial. The monitor reads in rounds, so it catches up first."""
        io_mon = self.io
        if io_mon is None:
            return None
        io_mon.catch_up(timeout_s=0.2)
        f = io_mon.follower
        return f.tick if f.trial == trial else None

    def next_trial(self) -> int:
        """The io channel's index (:attr:`bus.io_frames.TrialTickFollower.trial`) of the trial that
        starts next; the argument of :meth:`wait_trial_end` once it ran.  Call it before the
        start command, with the previous trial's end awaited (the io monitor is then up to date)."""
        io_mon = self.io
        return io_mon.follower.trial + 1 if io_mon is not None else 0

    def wait_trial_end(self, io_trial: int, end_stamp: float, timeout_s: float = 2.0) -> bool:
        """Wait until every frame of the trial that just ended is processed, by explicit markers
        (no reading rounds): the io monitor has seen the TRIAL_STOP of io trial ``io_trial``
        (:meth:`next_trial`), the other monitors a frame received at or after ``end_stamp``
        (``time.time()`` when the host learnt that the trial had ended; the caller makes sure a
        frame follows, e.g. by one more request).  Both monitors read unpaused meanwhile.  False
        (and a note in the log) when a marker did not come within ``timeout_s``: the trial is kept
        all the same, as after the rounds this replaces."""
        deadline = time.monotonic() + timeout_s
        with contextlib.ExitStack() as stack:
            for m in self.monitors:
                stack.enter_context(m.unpaused())
            missing = [
                m.name for m in self.monitors if not m.wait_until(_end_seen(m, io_trial, end_stamp), deadline - time.monotonic())
            ]
        if missing:
            logger.info("end of trial: no marker on %s within %g s", ", ".join(missing), timeout_s)
        return not missing

    def catch_up(self) -> None:
        """Wait until every monitor has processed the frames that reached it before the call
        (:meth:`ChannelMonitor.catch_up`)."""
        for m in self.monitors:
            m.catch_up()

    def bus_errors(self) -> list[BusError]:
        """The monitors whose bus failed, in channel order."""
        return [BusError(m.name, m.bus_error, m.bus_error_t) for m in self.monitors if m.bus_error is not None]

    def troubles(self) -> list[ChannelTrouble]:
        """Per channel, a stopped log and the bus error frames seen (only channels with either)."""
        return [
            ChannelTrouble(
                m.name,
                m.log_error,
                m.log_error_t,
                m.log_disk_full,
                m.error_frames,
                m.first_error_frame_t,
                m.overflow_frames,
                m.first_overflow_t,
            )
            for m in self.monitors
            if m.log_error is not None or m.error_frames
        ]

    def info(self, wall_s: float) -> dict[str, Any]:
        """Per channel: frames and bits since the host started (the monitors catch up first), the
        emulator's throughput over ``wall_s`` seconds, the log's name and the error frames."""
        channels = {}
        for m in self.monitors:
            m.catch_up()
            with m.lock:
                c = m.counter
                channels[m.name] = {
                    **c.as_dict(),
                    "emulator_throughput_bits_per_s": c.bits_worst_case / wall_s if wall_s > 0 else 0.0,
                    "log": f"{m.name}.log" if m.log is not None or m.log_error else None,
                    "error_frames": m.error_frames,
                    "overflow_frames": m.overflow_frames,
                }
        return channels

    def close(self) -> None:
        """Stop every monitor (its log and bus closed). Never raises."""
        for m in self.monitors:
            try:
                m.close()
            except Exception:  # noqa: BLE001 - closing must never hide the original error
                logger.warning("closing the %s monitor failed", m.name, exc_info=True)
        self.monitors = []


def _end_seen(monitor: ChannelMonitor, io_trial: int, end_stamp: float) -> Callable[[], bool]:
    """The end-of-trial marker of ``monitor`` (:meth:`RigChannels.wait_trial_end`)."""
    if monitor.name == IO:
        follower = monitor.follower
        return lambda: follower.ended >= io_trial
    return lambda: monitor.last_stamp >= end_stamp

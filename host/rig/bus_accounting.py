"""The rig's bus time in emulated time: what the experiment's traffic would take on real buses.

This module owns the host's reading of the two channels' traffic (classified by
:mod:`bus.traffic`, fed by the channel monitors of :mod:`host.rig.monitor`) against each channel's
bit rate (``--io-bitrate``, ``--fieldbus-bitrate``, default 1 Mbit/s), in ``summary.json``
(:meth:`BusTimeAccounting.summary`, key ``bus_time``) and on the console (:func:`bus_time_lines`):

* **during trials**, io channel: bits per control period (mean, worst tick) against the capacity
  ``bitrate × Ts``, and whether they fit (if not, by how much); fieldbus: nothing the experiment
  sends (SDO happens between trials only) — the heartbeats (every ``HEARTBEAT_MS`` of each node)
  are shown per period as a model in emulated time;
* **between trials**, fieldbus: the SDO exchange of one trial — feed-forward table downloads,
  arming and starting the trial, recorder uploads (:data:`PER_TRIAL_OBJECTS`) — in bits and in
  seconds at the bit rate, i.e. the dwell between two pick-and-place trials the exchange needs
  and the cycle it makes;
* **once per run**: the set-up exchange (gains, reference tables, enabling, configuration);
* **counted apart**, because their amount depends on how fast the emulator runs, not on the
  experiment: the status polls of the running trial (0x2410:4–8), the boot-wait polls (0x1000),
  heartbeats and boot-ups, and the emulator's timing diagnostics (0x2440, and 0x2441 after a trial
  with deadline misses); EMCY frames (faults).

Everything is counted by what a frame is (COB-ID, SDO object), never by when it was seen, so two
runs of one configuration report identical figures for the traffic the experiment defines.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import can
import numpy as np

from bus.busload import frame_bits_worst_case
from bus.errors import InputError
from bus.objects import DRIVE_NODE_IDS, Obj
from bus.plant_objects import DEFAULT_PLANT_NODE_ID, PlantObj, PlantTrialSub
from bus.traffic import DEFAULT_BITRATE, IoTickCounter, SdoKey, SdoTransferCounter, TickBudget, bits_to_s

logger = logging.getLogger(__name__)

__all__ = ["BusTimeAccounting", "PER_TRIAL_OBJECTS", "bus_time_lines", "kind_of"]

#: the SDO transfers of one trial, (index, direction) → kind, per node group
PER_TRIAL_OBJECTS: dict[str, dict[tuple[int, str], str]] = {
    "drive": {
        (int(Obj.FEEDFORWARD_TABLE), "download"): "feed-forward table downloads",
        (int(Obj.TABLE), "upload"): "trial set-up",
        (int(Obj.TRIAL), "download"): "trial set-up",
        (int(Obj.RECORDER), "upload"): "recorder uploads",
        (int(Obj.RECORDER_DATA), "upload"): "recorder uploads",
    },
    "bench": {
        (int(PlantObj.INITIAL_STATE), "download"): "trial set-up",
        (int(PlantObj.TRIAL), "download"): "trial set-up",
    },
}
_STATUS_SUBS = {
    int(s)
    for s in (
        PlantTrialSub.STATUS,
        PlantTrialSub.TICKS_DONE,
        PlantTrialSub.FAULT_CODE,
        PlantTrialSub.FAULT_TICK,
        PlantTrialSub.FAULT_NODE,
    )
}
SPEED_NOTE = (
    "counted apart: the amount depends on how fast the emulator runs (wall-clock polls and heartbeats), not on the experiment"
)


def kind_of(key: SdoKey) -> tuple[str, str]:
    """(group, kind) of an SDO transfer: group ``per_trial``, ``setup``, ``speed_dependent`` or
    ``diagnostics``."""
    node, index, sub, direction = key
    if node == DEFAULT_PLANT_NODE_ID:
        if index == PlantObj.TRIAL and direction == "upload" and sub in _STATUS_SUBS:
            return "speed_dependent", "status polls"
        if index in (PlantObj.TRIAL_TIMING, PlantObj.DEADLINE_MISSES):
            return "diagnostics", "timing diagnostics (0x2440, 0x2441)"
        group = "bench"
    elif node in DRIVE_NODE_IDS:
        group = "drive"
    else:
        return "setup", "other nodes"
    if index == Obj.DEVICE_TYPE and direction == "upload":
        return "speed_dependent", "boot-wait polls"
    kind = PER_TRIAL_OBJECTS[group].get((index, direction))
    if kind is not None:
        return "per_trial", kind
    return "setup", "set-up"


class BusTimeAccounting:
    """The two channels' classifiers and the figures built from them (module docstring).

    :param io_bitrate: io channel bit rate, bit/s
    :param fieldbus_bitrate: fieldbus bit rate, bit/s
    :param ts_s: control period, s
    :param trial_s: duration of one trial ((N − 1)·Ts), s
    :param heartbeat_ms: producer heartbeat period of every node, ms
    :param n_nodes: nodes that send heartbeats
    """

    def __init__(
        self,
        *,
        io_bitrate: int = DEFAULT_BITRATE,
        fieldbus_bitrate: int = DEFAULT_BITRATE,
        ts_s: float,
        trial_s: float,
        heartbeat_ms: int,
        n_nodes: int,
    ) -> None:
        for name, rate in (("io_bitrate", io_bitrate), ("fieldbus_bitrate", fieldbus_bitrate)):
            if int(rate) != rate or rate <= 0:
                raise InputError(f"{name} must be a positive integer in bit/s, got {rate!r}")
        self.io_bitrate = int(io_bitrate)
        self.fieldbus_bitrate = int(fieldbus_bitrate)
        self.ts_s = ts_s
        self.trial_s = trial_s
        self.heartbeat_ms = heartbeat_ms
        self.n_nodes = n_nodes
        self.io = IoTickCounter()
        self.fieldbus = SdoTransferCounter()
        self._lock = threading.Lock()

    def add_io(self, msg: can.Message) -> None:
        """Classify one io frame (called by the io monitor, in order)."""
        with self._lock:
            self.io.add(msg)

    def add_io_frames(self, frames: np.ndarray) -> None:
        """Classify many io frames at once (an array of :data:`bus.bus_features.FRAME_DTYPE`, in
        order; the same counts as :meth:`add_io` one by one)."""
        with self._lock:
            self.io.add_frames(frames)

    def add_fieldbus(self, msg: can.Message) -> None:
        """Classify one fieldbus frame (called by the fieldbus monitor, in order)."""
        with self._lock:
            self.fieldbus.add(msg)

    def summary(self, trials: int) -> dict[str, Any]:
        """The ``bus_time`` entry of ``summary.json`` after ``trials`` completed trials."""
        with self._lock:
            self.io.close()
            return {
                "io": self._io_summary(trials),
                "fieldbus": self._fieldbus_summary(trials),
                "basis": "emulated time: classic CAN frames, worst-case bit stuffing (docs/canopen-objects.md §9), "
                "at each channel's bit rate; frames counted by COB-ID and SDO object, never by wall time",
            }

    def _io_summary(self, trials: int) -> dict[str, Any]:
        io = self.io
        budget = TickBudget(self.io_bitrate, self.ts_s)
        return {
            "bitrate": self.io_bitrate,
            "control_period_s": self.ts_s,
            "capacity_bits_per_tick": budget.capacity_bits,
            "ticks": io.ticks,
            "frames_in_ticks": io.frames,
            "mean_tick": budget.fit(io.bits_mean),
            "worst_tick": budget.fit(io.bits_max),
            "control_frames": io.control_frames,
            "control_bits_per_trial": io.control_bits / trials if trials else 0.0,
            "other_frames": io.other_frames,
        }

    def _fieldbus_summary(self, trials: int) -> dict[str, Any]:
        rate = self.fieldbus_bitrate
        groups: dict[str, dict[str, dict[str, float]]] = {}
        per_trial: dict[str, dict[str, float]] = {}  # one transfer of each per-trial object
        for key, tally in sorted(self.fieldbus.sdo.items()):
            group, kind = kind_of(key)
            entry = groups.setdefault(group, {}).setdefault(kind, {"frames": 0, "bits": 0, "transfers": 0})
            entry["frames"] += tally.frames
            entry["bits"] += tally.bits
            entry["transfers"] += tally.transfers
            if group == "per_trial" and tally.transfers:
                one = per_trial.setdefault(kind, {"frames": 0.0, "bits": 0.0})
                one["frames"] += tally.frames / tally.transfers
                one["bits"] += tally.bits / tally.transfers
        per_trial_bits = sum(e["bits"] for e in per_trial.values()) if trials else 0.0
        per_trial_s = bits_to_s(per_trial_bits, rate)
        setup = groups.get("setup", {})
        setup_bits = sum(e["bits"] for e in setup.values())
        classes = {name: {"frames": t.frames, "bits": t.bits} for name, t in sorted(self.fieldbus.classes.items())}
        heartbeat_bits = frame_bits_worst_case(1)
        beats_per_tick = self.n_nodes * self.ts_s / (self.heartbeat_ms / 1000.0) if self.heartbeat_ms else 0.0
        budget = TickBudget(rate, self.ts_s)
        return {
            "bitrate": rate,
            "during_trials": {
                "experiment_bits_per_tick": 0,
                "note": "the experiment sends nothing on the fieldbus during a trial (SDO only between trials)",
                "heartbeat_model": {
                    "period_ms": self.heartbeat_ms,
                    "nodes": self.n_nodes,
                    "bits_per_heartbeat": heartbeat_bits,
                    "mean_tick": budget.fit(beats_per_tick * heartbeat_bits),
                    "worst_tick": budget.fit(self.n_nodes * heartbeat_bits if self.heartbeat_ms else 0),
                },
            },
            "between_trials": {
                "trials": trials,
                "basis": "one transfer of each object the host moves per trial (bits of the transfers of an object / "
                "their number: the same for every trial, as the sizes are)",
                "bits_per_trial": per_trial_bits,
                "seconds_per_trial": per_trial_s,
                "by_kind_per_trial": {
                    k: {"frames": e["frames"], "bits": e["bits"], "seconds": bits_to_s(e["bits"], rate)}
                    for k, e in sorted(per_trial.items())
                }
                if trials
                else {},
                "trial_motion_s": self.trial_s,
                "dwell_needed_s": per_trial_s,
                "cycle_s": self.trial_s + per_trial_s,
                "motion_share_percent": 100.0 * self.trial_s / (self.trial_s + per_trial_s)
                if self.trial_s + per_trial_s > 0
                else 0.0,
            },
            "once_per_run": {
                "bits": setup_bits,
                "seconds": bits_to_s(setup_bits, rate),
                "by_kind": {k: dict(e) for k, e in sorted(setup.items())},
            },
            "counted_apart": {
                "note": SPEED_NOTE,
                "sdo": {k: dict(e) for g in ("speed_dependent", "diagnostics") for k, e in sorted(groups.get(g, {}).items())},
                "frames_by_class": classes,
            },
        }


def bus_time_lines(bt: dict[str, Any]) -> list[str]:
    """Console lines of :meth:`BusTimeAccounting.summary`."""
    io, fb = bt["io"], bt["fieldbus"]
    mean, worst = io["mean_tick"], io["worst_tick"]
    cap = io["capacity_bits_per_tick"]
    if worst["fits"]:
        verdict = "fits"
    else:
        verdict = (
            f"does NOT fit: {worst['excess_bits']:.0f} bits over ({worst['excess_percent_of_capacity']:.0f} % over "
            f"the capacity; a tick needs {worst['time_needed_s'] * 1e3:.3f} ms)"
        )
    lines = [
        f"bus time (emulated) io at {io['bitrate'] / 1e3:g} kbit/s: per tick {mean['bits']:.0f} bits mean, "
        f"{worst['bits']:.0f} worst of {cap:.0f} ({min(worst['utilisation_percent'], 100.0):.1f} %): {verdict}"
    ]
    bt_ = fb["between_trials"]
    lines.append(
        f"bus time (emulated) fieldbus at {fb['bitrate'] / 1e3:g} kbit/s: between trials "
        f"{bt_['seconds_per_trial']:.3f} s per trial (feed-forward tables, trial set-up, recorder uploads) "
        f"-> a dwell of >= {bt_['dwell_needed_s']:.3f} s after each {bt_['trial_motion_s']:.3f} s trial, "
        f"cycle {bt_['cycle_s']:.3f} s ({bt_['motion_share_percent']:.0f} % in motion); once per run "
        f"{fb['once_per_run']['seconds']:.3f} s; polls and heartbeats counted apart (emulator-speed dependent)"
    )
    return lines

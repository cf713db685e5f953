"""Benchmark: ``ilcrig robot`` driven by a master that answers at once, beside the bare lockstep floor.

Two measurements on the default transport (the zero-privilege hub), each with the load average:

* **SYNC-stepped** (``ilcrig robot``, deterministic time): a raw python-can master on the fieldbus
  (set up once through python canopen: RPDO1 = controlword + target position, TPDO1 = statusword +
  position actual, CSP, the four drives enabled and holding) sends per control period its four
  RPDOs and one SYNC and waits for the four TPDOs before the next period — the robot steps one
  period per SYNC, so the rate is the robot's: periods/s over ``--periods`` periods, best of
  ``--repeat``.  Beside it, measured alternately in the same run, the bare 5-process io lockstep on
  the same transport (benchmarks/transport_speed.py, the floor of benchmarks/rig_speed.py).
  Target: >= 2,000 periods/s on 2 cores.  With it, the CPU time per period of every process over
  the measured periods (the kernel's run time of each of its threads, ``/proc/<pid>/task/*/schedstat``):
  the hub, the plant, each drive, the launcher (its channel monitors) and the master's thread;
  and the times per period each process was put on a CPU (its wake-ups and preemptions, the
  schedstat's third field).
* **real time** (``ilcrig robot --realtime``): the master sends SYNC + RPDOs at 1 kHz on its own
  clock (t0 + k·1 ms; SCHED_FIFO one step above the robot, as a master on a machine of its own
  would not be starved by the robot) and takes the TPDOs as they come; the robot paces its periods
  to the wall clock.  Over ``--seconds`` after a warm-up, the plant's own counters (0x2450, read by
  SDO from inside the master's cycle at the window's start and end): late periods (started after
  their window or completed after the next period's time, each once), missing SYNCs (whole periods
  without one) and SYNC overruns, all of them over the periods stepped; and the same without the
  cycles the master itself skipped (its timer came more than 100 µs late: each is a missing SYNC
  that no robot could have had).  Target: <= 0.1 % on a quiet machine, judged on the second.  The
  CPU time the hypervisor took meanwhile (steal) is printed with it.

``--waits`` (root) records the wake-ups of each real-time run in a kernel trace, as
``benchmarks/rt_attribution.py --waits`` does for ``ilcrig run``, and says over the master's window
where the robot's processes waited for a CPU and who held it.

    python benchmarks/robot_speed.py [--periods 5000] [--repeat 3] [--seconds 10] [--only sync|realtime] [--rounds N] [--waits]
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(REPO))

import can  # noqa: E402
import numpy as np  # noqa: E402
from robot_util import DRIVES, PLANT_ID, RPDO_LAYOUT, LockstepMaster, RobotProcess, counts_of  # noqa: E402

from bus import run_queue  # noqa: E402
from bus.bus_features import batch_sender  # noqa: E402
from bus.fastmsg import new_message  # noqa: E402
from bus.plant_objects import PlantObj, RobotSub  # noqa: E402
from bus.timer_slack import fine_timer_slack  # noqa: E402
from host.rig.realtime import cpu_steal_s  # noqa: E402
from plant.kinematics import inverse_kinematics  # noqa: E402
from plant.mechanics import HOME_POSE  # noqa: E402


def floor() -> float | None:
    """The bare 5-process io lockstep on the hub, ticks/s (benchmarks/transport_speed.py)."""
    import transport_speed as bt

    res = bt.run_transport("hub-unix", argparse.Namespace(seconds=1.0, pings=200, only=["hub-unix"], modes=["io"]))
    return (res.get("io") or {}).get("ticks_per_s")


def sched_stat(pid: int) -> tuple[float, int]:
    """CPU time [s] process ``pid`` has run so far, all its threads, and the times they were put
    on a CPU (:func:`bus.run_queue.sched_stat`)."""
    stat = run_queue.sched_stat(pid)
    return (0.0, 0) if stat is None else (stat.run_s, stat.slices)


def set_up(where: dict[str, Any]) -> dict[int, int]:
    """PDOs, NMT start, CSP, the drives enabled at the home pose (python canopen); the targets."""
    m = LockstepMaster(interface=where["interface"], channel=where["channel"])
    try:
        m.configure()
        m.start()
        home = counts_of(inverse_kinematics(np.array(HOME_POSE)))
        m.enable(home)
        return home
    finally:
        m.close()


def raw_bus(where: dict[str, Any]) -> can.BusABC:
    """The master's bus: the drives' TPDO1s and the plant node's SDO answers."""
    bus = can.Bus(interface=where["interface"], channel=where["channel"])
    ids = [0x180 + n for n in DRIVES] + [0x580 + PLANT_ID]
    bus.set_filters([{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in ids])
    return bus


def period_frames(home: dict[int, int]) -> list[can.Message]:
    """The four RPDOs (Enable operation, hold at home) and the SYNC of one period."""
    rpdos = [new_message(0x200 + n, bytearray(RPDO_LAYOUT.pack(0x0F, home[n]))) for n in DRIVES]
    return [*rpdos, new_message(0x080, bytearray())]


def master_of(robot: RobotProcess) -> tuple[dict[str, Any], can.BusABC, Callable[[list[can.Message]], None], list[can.Message]]:
    """The robot ready and set up (:func:`set_up`): where it is, the master's bus, its batch sender and
    the frames of one period."""
    where = robot.ready()
    home = set_up(where)
    bus = raw_bus(where)
    return where, bus, batch_sender(bus), period_frames(home)


def sync_stepped(periods: int) -> dict[str, Any]:
    """``ilcrig robot``, a master waiting for the TPDOs every period: periods/s."""
    with tempfile.TemporaryDirectory() as tmp:
        robot = RobotProcess(Path(tmp) / "robot")
        try:
            where, bus, send, frames = master_of(robot)
            pids = {**where["pids"], "launcher": robot.proc.pid}
            stat0: dict[str, tuple[float, int]] = {}
            try:
                for k in range(periods + 200):
                    if k == 200:  # the first 200 periods warm up
                        stat0 = {name: sched_stat(pid) for name, pid in pids.items()}
                        master0 = time.thread_time()
                        t0 = time.perf_counter()
                    send(frames)
                    got = 0
                    while got < len(DRIVES):
                        msg = bus.recv(timeout=5.0)
                        if msg is None:
                            raise TimeoutError(f"period {k}: TPDOs missing")
                        got += 1
                rate = periods / (time.perf_counter() - t0)
                stat1 = {name: sched_stat(pid) for name, pid in pids.items()}
                cpu_us = {name: (stat1[name][0] - stat0[name][0]) / periods * 1e6 for name in pids}
                runs = {name: (stat1[name][1] - stat0[name][1]) / periods for name in pids}
                cpu_us["master"] = (time.thread_time() - master0) / periods * 1e6
            finally:
                bus.shutdown()
            robot.stop()
            summary = json.loads((robot.out / "summary.json").read_text())
            return {"periods_per_s": rate, "overruns": summary["robot"]["sync_overruns"], "cpu_us": cpu_us, "runs": runs}
        finally:
            robot.kill()


#: the robot's counters read by the 1 kHz master at the start and the end of its window (0x2450)
RT_COUNTERS = {
    "periods": RobotSub.PERIODS,
    "late_syncs": RobotSub.LATE_SYNCS,
    "missing_syncs": RobotSub.MISSING_SYNCS,
    "overruns": RobotSub.SYNC_OVERRUNS,
    "late_periods": RobotSub.LATE_PERIODS,
}
#: the last part of the master's wait for a cycle, spent on the clock (a wake-up from sleep can be late), s
MASTER_SPIN_S = 150e-6
#: the master sends a cycle's frames at most this long after its time, else it skips the cycle, s
MASTER_JITTER_S = 100e-6
#: periods the 1 kHz master sends before its window opens (the first SYNC after the set-up's pause
#: counts the pause as missing periods: the window leaves it out)
RT_WARM_UP = 200


#: an SDO frame's command byte and multiplexer (index LE, sub-index), CiA 301 §7.2.4.3
_SDO_MUX = struct.Struct("<BHB")


def sdo_upload_request(sub: int) -> can.Message:
    """An expedited SDO upload request for 0x2450:``sub`` to the plant node (CiA 301 §7.2.4.3.3)."""
    return new_message(0x600 + PLANT_ID, bytearray(_SDO_MUX.pack(0x40, PlantObj.ROBOT, sub) + bytes(4)))


class CounterReader:
    """The robot's 0x2450 counters, read by raw SDO frames from inside the master's cycle (no
    second client on the bus, no pause in the SYNCs): :meth:`request` sends the uploads, :meth:`take`
    looks at every frame the master receives."""

    def __init__(self, send: Any) -> None:
        self._send = send
        self.values: dict[str, int] = {}
        self._waiting: list[tuple[str, RobotSub]] = []

    def request(self) -> None:
        self.values = {}
        self._waiting = list(RT_COUNTERS.items())
        self._send([sdo_upload_request(self._waiting[0][1])])

    @property
    def done(self) -> bool:
        return not self._waiting

    def take(self, msg: can.Message) -> None:
        if not self._waiting or msg.arbitration_id != 0x580 + PLANT_ID:
            return
        name, sub = self._waiting[0]
        data = bytes(msg.data)
        ccs, index, got = _SDO_MUX.unpack_from(data)
        if ccs & 0xE0 != 0x40 or (index, got) != (PlantObj.ROBOT, sub):
            raise RuntimeError(f"unexpected SDO answer {data.hex()} to the upload of 0x{int(PlantObj.ROBOT):04X}:{int(sub)}")
        self.values[name] = int.from_bytes(data[4:8], "little")
        self._waiting.pop(0)
        if self._waiting:  # one transfer at a time, as an SDO client does
            self._send([sdo_upload_request(self._waiting[0][1])])


def realtime(seconds: float, rt_priority: int | None = None, spin_s: float = MASTER_SPIN_S) -> dict[str, Any]:
    """``ilcrig robot --realtime`` with a 1 kHz master: the robot's late periods in the master's window.

    The master runs in SCHED_FIFO one step above the robot's processes (a master is a machine of
    its own; here it shares the CPUs, and a starved master would measure itself): it sleeps to
    :data:`MASTER_SPIN_S` before each period's time (fine timer slack), waits the rest on the
    clock, sends the four RPDOs and the SYNC, and takes the TPDOs as
    they come. A cycle it reaches more than :data:`MASTER_JITTER_S` late is skipped and counted as
    the master's (the robot counts the period as missing): every SYNC sent left on time, so a late
    period of the robot is the robot's own. The window opens after :data:`RT_WARM_UP`
    periods: the robot's counters (0x2450) are read by SDO then and after the last period.
    ``rt_priority``: the robot's ``--rt-priority`` (None: its default, SCHED_FIFO where allowed; 0: normal
    scheduling, what a user without CAP_SYS_NICE gets — the master then takes SCHED_FIFO 1 above it).
    ``spin_s``: the master's wait on the clock before each cycle (``--master-spin-us``; 0: it sleeps to
    the cycle's time and skips the cycles its wake-up reached late)."""
    ts = 1e-3
    with tempfile.TemporaryDirectory() as tmp:
        rt_args = () if rt_priority is None else ("--rt-priority", str(rt_priority))
        robot = RobotProcess(Path(tmp) / "robot", "--realtime", *rt_args)
        try:
            where, bus, send, frames = master_of(robot)
            counters = CounterReader(send)
            robot_priority = max(os.sched_getparam(pid).sched_priority for pid in where["pids"].values())
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(robot_priority + 1))
                fifo = True
            except (OSError, AttributeError):
                fifo = False
            fine_timer_slack()
            n = RT_WARM_UP + int(seconds / ts)
            start: dict[str, int] = {}
            steal0 = cpu_steal_s()
            t0 = time.monotonic() + 0.05
            late_master = 0
            try:
                for k in range(n):
                    if k == RT_WARM_UP:
                        counters.request()
                    due = t0 + k * ts
                    left = due - time.monotonic()
                    if left > spin_s:
                        time.sleep(left - spin_s)
                    while time.monotonic() < due:
                        pass
                    if time.monotonic() - due > MASTER_JITTER_S:
                        late_master += k >= RT_WARM_UP
                        continue
                    send(frames)
                    while (msg := bus.recv(timeout=0)) is not None:  # the TPDOs, as they come
                        counters.take(msg)
                    if k >= RT_WARM_UP and not start and counters.done:
                        start = counters.values
                window_s = (t0 + RT_WARM_UP * ts, time.monotonic())  # the master's window, CLOCK_MONOTONIC
                if not start:
                    raise RuntimeError("the robot's counters did not come in the master's window")
                counters.request()
                deadline = time.monotonic() + 5.0
                while not counters.done:
                    msg = bus.recv(timeout=max(0.0, deadline - time.monotonic()))
                    if msg is None:
                        raise TimeoutError("the robot's counters did not come after the master's window")
                    counters.take(msg)
                end = counters.values
            finally:
                if fifo:
                    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
                bus.shutdown()
            steal1 = cpu_steal_s()
            robot.stop()
            summary = json.loads((robot.out / "summary.json").read_text())
            rt = summary["robot"].get("realtime") or {}
            d = {name: (end[name] - start[name]) & 0xFFFFFFFF for name in RT_COUNTERS}
            late = d["late_periods"] + d["missing_syncs"] + d["overruns"]
            # a cycle the master skipped is one missing SYNC the robot could not have had
            own = d["late_periods"] + max(0, d["missing_syncs"] - late_master) + d["overruns"]
            return {
                "syncs_sent": n,
                **d,
                "relocks": rt.get("relocks"),
                "lateness_p99_us": rt.get("lateness_p99_us"),
                "lateness_max_us": rt.get("lateness_max_us"),
                "late_fraction": late / max(d["periods"], 1),
                "own_late_fraction": own / max(d["periods"], 1),
                "master_late": late_master,
                "master_fifo": fifo,
                "scheduling": summary.get("scheduling"),
                "steal_s": None if steal0 is None or steal1 is None else steal1 - steal0,
                "window_s": window_s,
            }
        finally:
            robot.kill()


def traced_realtime(seconds: float, rt_priority: int | None, spin_s: float) -> dict[str, Any]:
    """:func:`realtime` under a kernel trace of the wake-ups (``--waits``, root; the trace of
    ``benchmarks/rt_attribution.py --waits``): where the robot's processes waited for a CPU in the
    master's window, and who held it (``result["waits"]``, :func:`host.rig.wake_waits.summarise_waits`)."""
    from rt_attribution import WAIT_EVENTS, RoleWatcher, kernel_trace, trace_overruns

    from host.rig.wake_waits import parse_waits, summarise_waits

    watcher = RoleWatcher()
    watcher.root = os.getpid()  # the robot's processes descend from this benchmark
    watcher.names[os.getpid()] = "master"  # this process: its 1 kHz loop, SCHED_FIFO above the robot
    watcher.start()
    try:
        with kernel_trace(WAIT_EVENTS, record_tgid=True) as trace:
            r = realtime(seconds, rt_priority, spin_s)
            text = trace.read_text()
            r["trace_lost"] = trace_overruns()
    finally:
        watcher.done.set()
    r["waits"] = summarise_waits(parse_waits(text.splitlines(), [r["window_s"]]), watcher.roles, names=watcher.names)
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--periods", type=int, default=5000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--only", choices=("sync", "realtime"), default=None)
    ap.add_argument("--rounds", type=int, default=1, help="real time: rounds of (floor, fifo, normal), alternating")
    ap.add_argument(
        "--variant",
        action="append",
        choices=("fifo", "normal"),
        default=None,
        help="real time: the robot's scheduling to measure (repeatable; default both)",
    )
    ap.add_argument(
        "--master-spin-us",
        type=float,
        default=MASTER_SPIN_S * 1e6,
        help="real time: the last part of the master's wait for a cycle, spent on the clock, us (default %(default)g)",
    )
    ap.add_argument(
        "--waits",
        action="store_true",
        help="real time: a kernel trace of the wake-ups (root): where the robot's processes waited for a CPU, and who held it",
    )
    args = ap.parse_args()
    if args.waits and os.geteuid() != 0:
        raise SystemExit("robot_speed --waits: the kernel trace needs root (tracefs)")
    print(f"ilcrig robot benchmark: hub transport, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")
    if args.only in (None, "sync"):
        floors, rates = [], []
        load0 = os.getloadavg()[0]
        for _ in range(args.repeat):
            f = floor()
            if f:
                floors.append(f)
            r = sync_stepped(args.periods)
            rates.append(r["periods_per_s"])
            cpu = r["cpu_us"]
            roles = ", ".join(f"{name} {us:.0f}" for name, us in sorted(cpu.items()))
            runs = ", ".join(f"{name} {n:.2f}" for name, n in sorted(r["runs"].items()))
            print(
                f"  floor {f or float('nan'):,.0f} ticks/s; robot {r['periods_per_s']:,.0f} periods/s "
                f"({r['overruns']} overruns); CPU per period [us]: {roles}, "
                f"all {sum(cpu.values()):.0f}; on a CPU per period: {runs}; load average {os.getloadavg()[0]:.2f}",
                flush=True,
            )
        best = max(rates)
        print(
            f"SYNC-stepped: best {best:,.0f} periods/s (runs {' '.join(f'{x:,.0f}' for x in rates)}), floor best "
            f"{max(floors) if floors else float('nan'):,.0f} ticks/s, ratio "
            f"{best / max(floors) if floors else float('nan'):.2f}; load average {load0:.2f} -> "
            f"{os.getloadavg()[0]:.2f}; goal >= 2,000 periods/s: {'met' if best >= 2000 else 'NOT met'}"
        )
    if args.only in (None, "realtime"):
        # per round: the machine's floor for each scheduling class (a lone 1 kHz loop,
        # benchmarks/timer_latency.py), then the robot with SCHED_FIFO and without (--rt-priority 0),
        # in an order rotated from round to round
        from rt_compare import floor as timer_floor

        variants = [(name, prio) for name, prio in (("fifo", None), ("normal", 0)) if name in (args.variant or (name,))]
        for round_no in range(args.rounds):
            floors = {name: timer_floor(0 if prio == 0 else 1) for name, prio in variants}
            order = variants[round_no % 2 :] + variants[: round_no % 2]
            for name, prio in order:
                load0 = os.getloadavg()[0]
                r = (traced_realtime if args.waits else realtime)(args.seconds, prio, args.master_spin_us * 1e-6)
                fl = floors[name]
                steal = "n/a" if r["steal_s"] is None else f"{r['steal_s'] * 1e3:.0f} ms"
                print(
                    f"real time [{name}], 1 kHz master for {args.seconds:g} s (after {RT_WARM_UP} periods of warm-up): "
                    f"{r['periods']} periods, late periods {r['late_periods']} (late SYNCs {r['late_syncs']}), missing "
                    f"{r['missing_syncs']}, overruns {r['overruns']}: {100 * r['late_fraction']:.3f} % late, "
                    f"{100 * r['own_late_fraction']:.3f} % without the cycles the master skipped (goal <= 0.5 %: "
                    f"{'met' if r['own_late_fraction'] <= 5e-3 else 'NOT met'}); schedule re-locks "
                    f"{r['relocks']}; lateness p99 {r['lateness_p99_us']:.0f} us, max {r['lateness_max_us']:.0f} us; "
                    f"floor ({fl['scheduling']}) late {100 * fl['later_than_one_period'] / max(fl['periods'], 1):.3f} %, "
                    f"p99 {fl['lateness_p99_s'] * 1e6:.0f} us; master cycles skipped {r['master_late']} "
                    f"(SCHED_FIFO {r['master_fifo']}); scheduling {r['scheduling']}; steal {steal}; "
                    f"load average {load0:.2f} -> {os.getloadavg()[0]:.2f}",
                    flush=True,
                )
                if "waits" in r:
                    from rt_attribution import print_waits

                    head = f"robot_speed --waits [{name}]: {r['periods']} periods, {100 * r['own_late_fraction']:.3f} % late"
                    print_waits(r["waits"], head, r["trace_lost"])


if __name__ == "__main__":
    main()

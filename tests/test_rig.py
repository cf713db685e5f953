"""The distributed rig as separate OS processes: digest equality with ``ilcrig sim`` over the
zero-privilege hub and over udp_multicast inside a private network namespace; the canopen library
reading and writing drive objects of a drive process; candump logs read back with can.LogReader."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import can
import canopen
import pytest
from cli_util import run_in_session, stop_process
from drive402_util import vendor_id_once_up
from netns_util import NETNS_SETUP, netns_unavailable_reason

from bus.busload import bits_lookup
from bus.io_frames import ENCODER_COB_BASE, TORQUE_COB_BASE
from bus.objects import Obj
from bus.transports.config import hub_transport
from bus.transports.hub.process import start_hub
from bus.units import timeout_scale
from host.experiment.config import build_config
from host.experiment.plan import prepare
from host.experiment.trial_loop import run_experiment
from host.rig.cpu_latency import CPU_LATENCY_PATH
from host.rig.realtime import scheduling_mechanisms
from host.sim.inprocess import InProcessBench

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

EXP = ["--iterations", "2", "--cycle", "0.15", "--disturbance", "both", "--seed", "3"]
EXP_CFG = {"iterations": 2, "cycle_s": 0.15, "disturbance": "both", "seed": 3}
REPO = Path(__file__).resolve().parent.parent
DRIVE_EDS = REPO / "bus" / "drive.eds"


@pytest.fixture(scope="module")
def sim_digest() -> str:
    cfg = build_config(None, EXP_CFG)
    res = run_experiment(prepare(cfg), InProcessBench(cfg), None, mode="sim")
    return res.summary["trace_sha256"]


def run_rig(cmd: list[str], timeout_s: float = 300.0, cwd: Path = REPO) -> subprocess.CompletedProcess[str]:
    """Run a launcher command in its own session; kill the whole group if it hangs."""
    return run_in_session(cmd, timeout_s, cwd, what="rig")


#: trials and ticks per trial of EXP (a 0.15 s cycle is 2 × 0.15 s of motion at Ts = 1 ms, plus tick 0)
TRIALS, TICKS = 2, 301


def check_run(res: subprocess.CompletedProcess[str], out: Path, digest: str, transport: str) -> dict:
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["mode"] == "rig"
    assert s["completed"] is True and s["faults"] == []
    assert s["trace_sha256"] == digest
    assert [it["k"] for it in s["iterations"]] == list(range(TRIALS))
    assert s["ticks"] == TRIALS * TICKS
    assert f"{TRIALS * TICKS} ticks, " in res.stdout and f"trace_sha256 {digest[:16]}…" in res.stdout
    info = s["bench"]
    assert info["transport"]["name"] == transport
    fb, io = info["channels"]["fieldbus"], info["channels"]["io"]
    # io: per tick 4 encoder + 4 torque frames, plus start/stop control frames per trial
    assert io["frames"] == TRIALS * TICKS * 8 + TRIALS * 2
    assert fb["frames"] > 1000
    for ch, name in ((fb, "fieldbus"), (io, "io")):
        assert ch["error_frames"] == 0 and ch["log"] == f"{name}.log"
        assert ch["emulator_throughput_bits_per_s"] == pytest.approx(ch["bits_worst_case"] / info["elapsed_s"])
    timing = info["timing"]
    assert timing["trials"] == TRIALS and timing["ticks"] == TRIALS * TICKS
    assert [t["ticks"] for t in timing["per_trial"]] == [TICKS] * TRIALS
    assert timing["achieved_ticks_per_s"] == pytest.approx(timing["ticks"] / timing["duration_s"])
    assert info["heartbeat"] == {
        "host_node_id": 127,
        "host_period_ms": 200,
        "node_period_ms": 200,
        "consumer_time_ms": 500.0 * timeout_scale(),
        "host_stalls": [],
    }
    assert info["emcy"] == [] and info["recoveries"] == []
    bt = info["bus_time"]
    assert bt["io"]["ticks"] == TRIALS * TICKS and bt["io"]["worst_tick"]["bits"] == 960
    assert bt["fieldbus"]["between_trials"]["trials"] == TRIALS
    assert bt["fieldbus"]["between_trials"]["bits_per_trial"] > 0
    # every drive torque-free at the end, each shown by its own STOPPED heartbeat
    assert [(e["node"], e["torque"], e["nmt"]) for e in s["safe_state"]] == [
        (f"drive{n}", "off", "STOPPED") for n in (1, 2, 3, 4)
    ]
    assert all(
        e["evidence"].startswith("CiA 402 disable voltage, NMT STOP; its heartbeat reported STOPPED") for e in s["safe_state"]
    )
    return s


def experiment_bus_time(s: dict) -> dict:
    """The bus-time figures of the traffic the experiment defines (bits; seconds depend on the rate)."""
    bt = s["bench"]["bus_time"]
    between = bt["fieldbus"]["between_trials"]
    return {
        "io": {k: bt["io"][k] for k in ("ticks", "frames_in_ticks", "control_frames", "control_bits_per_trial")}
        | {"mean_bits": bt["io"]["mean_tick"]["bits"], "worst_bits": bt["io"]["worst_tick"]["bits"]},
        "between_trials": {k: between[k] for k in ("bits_per_trial", "trials")}
        | {kind: e["bits"] for kind, e in between["by_kind_per_trial"].items()},
    }


@pytest.fixture(scope="module")
def hub_run(tmp_path_factory: pytest.TempPathFactory, sim_digest: str) -> tuple[subprocess.CompletedProcess[str], Path, dict]:
    out = tmp_path_factory.mktemp("hub") / "rig"
    res = run_rig([sys.executable, "-m", "host.cli", "run", *EXP, "--bus", "hub", "--out", str(out)])
    return res, out, check_run(res, out, sim_digest, "hub")


@pytest.mark.fast
def test_rig_over_hub_equals_sim_and_logs_read_back(hub_run: tuple[subprocess.CompletedProcess[str], Path, dict]) -> None:
    res, out, s = hub_run
    assert "RMSE j1" in res.stdout
    io_frames = list(can.LogReader(out / "io.log"))
    assert len(io_frames) == s["bench"]["channels"]["io"]["frames"]
    ids = {m.arbitration_id for m in io_frames}
    assert {ENCODER_COB_BASE + j for j in range(4)} | {TORQUE_COB_BASE + j for j in range(4)} <= ids
    fb_frames = list(can.LogReader(out / "fieldbus.log"))
    # the summary counts up to the end of the last trial; the log also holds the shutdown
    # (drives disabled by SDO, NMT stop, last heartbeats)
    assert 0 <= len(fb_frames) - s["bench"]["channels"]["fieldbus"]["frames"] < 300
    assert any(m.arbitration_id == 0x601 for m in fb_frames)  # SDO requests to drive 1
    assert any(m.arbitration_id == 0x701 for m in fb_frames)  # heartbeats of drive 1
    # the plant prepared the run's disturbance alone (the launcher told it the experiment's)
    assert f"disturbance model ({EXP_CFG['disturbance']}) ready" in (out / "logs" / "plant.log").read_text()


def test_run_from_a_folder_holding_modules_named_like_the_packages(tmp_path: Path, sim_digest: str) -> None:
    """`ilcrig run` started in a folder that holds a plant.py, bus.py and host.py (each failing on
    import): no process of the rig imports them (the roles run in Python's safe-path mode, the hub
    with PYTHONSAFEPATH), so the run completes with the digest of `ilcrig sim`."""
    ilcrig = Path(sys.executable).with_name("ilcrig")
    assert ilcrig.is_file(), f"the ilcrig console script is not installed next to {sys.executable}"
    work = tmp_path / "work"
    work.mkdir()
    for name in ("plant", "bus", "host"):
        (work / f"{name}.py").write_text(f"raise ImportError('{name}.py of the working folder was imported')\n")
    out = tmp_path / "rig"
    res = run_rig([str(ilcrig), "run", *EXP, "--bus", "hub", "--out", str(out)], cwd=work)
    check_run(res, out, sim_digest, "hub")
    logs = {p.name: p.read_text() for p in (out / "logs").glob("*.log")}
    assert {"hub.log", "plant.log", "drive1.log", "drive4.log", "host.log"} <= set(logs)
    assert not any("of the working folder was imported" in text for text in logs.values())


def _idle_loops_left() -> list[int]:
    """Live processes running the idle-poll loop (host/rig/idle_poll.py: ``python -S -c CODE
    LAUNCHER_PID NICE``) whose launcher has ended — those of a run still going on the machine (another
    test session's) are not this run's."""
    left = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if stat.read_text().rsplit(")", 1)[1].split()[0] == "Z":
                continue
            argv = (stat.parent / "cmdline").read_bytes().split(b"\0")
            if any(b"os.SCHED_IDLE" in a for a in argv):
                code = next(k for k, a in enumerate(argv) if b"os.SCHED_IDLE" in a)
                launcher = int(argv[code + 1])
                if not Path(f"/proc/{launcher}").exists():
                    left.append(int(stat.parent.name))
        except (OSError, IndexError, ValueError, StopIteration):
            continue
    return left


@pytest.mark.alone  # holds the kernel's CPU latency request, the machine's (pyproject.toml)
def test_realtime_run_has_the_same_results_and_bus_time_figures(
    tmp_path: Path, sim_digest: str, hub_run: tuple[subprocess.CompletedProcess[str], Path, dict]
) -> None:
    """A second run of the same experiment, paced to the wall clock and accounted at 500 kbit/s on
    the io channel: the same digest, the same bits for every part of the traffic the experiment
    defines (io ticks, table downloads, trial set-up, recorder uploads), whatever the speed; the
    real-time statistics and the io verdict (960 bits do not fit 500 per period) are reported."""
    out = tmp_path / "rt"
    res = run_rig(
        [sys.executable, "-m", "host.cli", "run", *EXP, "--bus", "hub", "--realtime", "--io-bitrate", "500000", "--out", str(out)]
    )
    s = check_run(res, out, sim_digest, "hub")
    first = hub_run[2]
    assert experiment_bus_time(s) == experiment_bus_time(first)
    timing = s["bench"]["timing"]
    assert timing["mode"] == "realtime" and timing["ticks"] == 2 * 301
    assert {"deadline_misses", "lateness_p50_s", "lateness_p99_s", "lateness_max_s", "kept_up"} <= set(timing)
    # the launcher scheduled the lockstep processes: SCHED_FIFO where permitted, else it says why not
    sched = dict(timing["scheduling"])
    fifo = sched["policy"] == "SCHED_FIFO"
    assert sched.pop("mechanisms") == scheduling_mechanisms(timing["scheduling"])
    assert sched.pop("in_roles") == {"heap_frozen": True, "timer_slack_ns": 1000, "plant_spins": fifo}
    # idle CPUs kept out of halt where the PM QoS device may be written (root), in both classes
    if os.access(CPU_LATENCY_PATH, os.W_OK):
        assert sched.pop("cpu_latency") == {"latency_us": 0}
    else:
        assert "reason" in sched.pop("cpu_latency")
    roles = ["hub", "plant", "drive1", "drive2", "drive3", "drive4"]
    if fifo:  # ... and kept the CPUs awake with a SCHED_IDLE busy loop per CPU, all gone after the run
        assert sched.pop("idle_poll") == {"loops": len(os.sched_getaffinity(0))}
        assert "CPUs kept awake by" in res.stdout
        assert sched == {"policy": "SCHED_FIFO", "priority": 10, "roles": roles}
    else:  # normal scheduling made prompt, without busy loops, and the line says why
        assert sched.pop("idle_poll") == {"loops": 0, "reason": "not beside normal scheduling"}
        assert "not permitted" in sched["reason"] and sched["roles"] == roles and sched["host"] == {"policy": "SCHED_BATCH"}
        assert "normal scheduling (SCHED_FIFO 10 not permitted" in res.stdout
    assert not _idle_loops_left()
    io = s["bench"]["bus_time"]["io"]
    assert io["bitrate"] == 500_000 and not io["worst_tick"]["fits"] and io["worst_tick"]["excess_bits"] == 460
    assert "real time:" in res.stdout and "does NOT fit" in res.stdout
    apart = s["bench"]["bus_time"]["fieldbus"]["counted_apart"]
    assert "emulator" in apart["note"] and apart["sdo"]["status polls"]["frames"] > 0


def test_bus_time_hub_gives_the_same_results_and_real_bus_spacing(
    tmp_path: Path, sim_digest: str, hub_run: tuple[subprocess.CompletedProcess[str], Path, dict]
) -> None:
    """``--bus-time`` with io at 500 kbit/s: the hub carries both channels as real buses would, so
    the results and the experiment's bits are the same, and in both candump logs (timestamps: the end
    of each frame on the hub's virtual bus clock) no frame follows the previous one sooner than its
    own bit time at the channel's rate."""
    out = tmp_path / "bt"
    res = run_rig(
        [sys.executable, "-m", "host.cli", "run", *EXP, "--bus", "hub", "--bus-time", "--io-bitrate", "500000", "--out", str(out)]
    )
    s = check_run(res, out, sim_digest, "hub")
    assert experiment_bus_time(s) == experiment_bus_time(hub_run[2])
    assert s["bench"]["bus_time_hub"] == {"fieldbus": 1_000_000, "io": 500_000}
    assert "bus-time hub: io at 500 kbit/s, fieldbus at 1000 kbit/s" in res.stdout
    for name, rate in (("io", 500_000), ("fieldbus", 1_000_000)):
        frames = list(can.LogReader(out / f"{name}.log"))
        assert len(frames) > 1000
        for prev, m in zip(frames, frames[1:]):
            n = 0 if m.is_remote_frame else len(m.data)
            assert m.timestamp - prev.timestamp >= bits_lookup(n, m.is_extended_id)[1] / rate - 2e-6, (name, prev, m)


@pytest.mark.netns
@pytest.mark.fast
def test_rig_over_udp_multicast_in_private_netns_equals_sim(tmp_path: Path, sim_digest: str) -> None:
    reason = netns_unavailable_reason()
    if reason:
        pytest.skip(reason)
    out = tmp_path / "rig"
    inner = " ".join([sys.executable, "-m", "host.cli", "run", *EXP, "--bus", "udp_multicast", "--out", str(out)])
    res = run_rig(["unshare", "-rn", "sh", "-c", f"{NETNS_SETUP} && ILCRIG_PRIVATE_NETNS=1 exec {inner}"])
    check_run(res, out, sim_digest, "udp_multicast")


def test_canopen_library_reads_and_writes_a_drive_process(tmp_path: Path) -> None:
    with start_hub() as hub:
        drive = subprocess.Popen(
            [sys.executable, "-m", "host.cli", "drive", "--node", "2", "--bus", "hub", "--hub", hub.address],
            start_new_session=True,
            cwd=REPO,
        )
        network = canopen.Network(hub_transport(hub.address).open("fieldbus"))
        try:
            network.connect()
            node = network.add_node(2, str(DRIVE_EDS))
            node.sdo.RESPONSE_TIMEOUT = 2.0
            assert vendor_id_once_up(node, drive, 30.0) == node.object_dictionary[0x1018][1].default
            assert node.sdo[0x6041].raw & 0x004F == 0x0040  # switch on disabled
            node.sdo[0x6040].raw = 0x0006  # shutdown -> ready to switch on
            assert node.sdo[0x6041].raw & 0x006F == 0x0021
            node.sdo[0x6040].raw = 0x000F  # switch on + enable operation
            assert node.sdo[0x6041].raw & 0x006F == 0x0027
            node.sdo[0x6065].raw = 12345  # following-error window, counts
            assert node.sdo[0x6065].raw == 12345
            with pytest.raises(canopen.SdoAbortedError) as exc:
                node.sdo[0x6041].raw = 0  # statusword is read-only
            assert exc.value.code == 0x06010002
            with pytest.raises(canopen.SdoAbortedError) as exc:
                node.sdo.upload(0x5FFF, 0)
            assert exc.value.code == 0x06020000
            assert int(Obj.RECORDER_DATA) in node.object_dictionary
        finally:
            network.disconnect()
            stop_process(drive)
        assert drive.returncode == 0


def test_drive_killed_and_restarted_between_trials_is_set_up_again(tmp_path: Path) -> None:
    """Heartbeat loss + boot-up of drive 2 between trials: the host brings it up again,
    configures it and the next trial runs; the traces equal a run without the restart."""

    def role(*args: str, stdout: int = subprocess.DEVNULL, stderr: int | None = subprocess.DEVNULL) -> subprocess.Popen:
        """``ilcrig ROLE ARGS`` on the test's hub (output unbuffered: the host's rows as they come)."""
        return subprocess.Popen(
            [sys.executable, "-u", "-m", "host.cli", *args, "--bus", "hub", "--hub", hub.address],
            start_new_session=True,
            cwd=REPO,
            stdout=stdout,
            stderr=stderr,
            text=True,
        )

    procs: list[subprocess.Popen] = []
    with start_hub() as hub:
        try:
            drives = {n: role("drive", "--node", str(n)) for n in (1, 2, 3, 4)}
            procs += [*drives.values(), role("plant")]
            out = tmp_path / "rig"
            host_args = ("--iterations", "3", "--cycle", "0.15", "--pause", "4", "--recover", "60", "--out", str(out))
            host = role("host", *host_args, stdout=subprocess.PIPE, stderr=None)
            procs.append(host)
            lines = []
            for line in host.stdout:  # type: ignore[union-attr]
                lines.append(line)
                if line.split()[:1] == ["0"]:  # the row of trial 0: the host now pauses 4 s
                    drives[2].kill()
                    drives[2].wait()
                    procs.append(role("drive", "--node", "2"))
                    break
            lines += host.stdout.readlines()  # type: ignore[union-attr]
            assert host.wait(120) == 0, "".join(lines)
        finally:
            for p in procs:
                if p.poll() is None:
                    os.killpg(p.pid, signal.SIGTERM)
            for p in procs:
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
    s = json.loads((out / "summary.json").read_text())
    assert s["completed"] and len(s["iterations"]) == 3
    rec = s["bench"]["recoveries"]
    assert [r["node"] for r in rec] == [2] and rec[0]["before_trial"] == 1
    assert rec[0]["heartbeat_lost"] or rec[0]["boot_up_seen"]
    cfg = build_config(None, {"iterations": 3, "cycle_s": 0.15})
    ref = run_experiment(prepare(cfg), InProcessBench(cfg), None, mode="sim")
    assert s["trace_sha256"] == ref.summary["trace_sha256"]

"""Roles on separate hosts: two network namespaces joined by a veth pair that the test creates
(private addresses on that pair only; both namespaces, the pair and every process die with the
test), the hub (``--allow-remote``) and the four drives in one, the plant and the host in the
other, over TCP; the run's digest equals ``ilcrig sim``'s.  Also: the hub still refuses a
non-loopback address unless told explicitly."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from netns_util import netns_unavailable_reason

from bus.transports.config import hub_transport
from bus.transports.hub.addresses import parse_address
from bus.transports.hub.server import HubServer
from bus.transports.hub.wire import NonLoopbackAddressError
from host.experiment.config import build_config
from host.experiment.plan import prepare
from host.experiment.trial_loop import run_experiment
from host.sim.inprocess import InProcessBench

HERE = Path(__file__).resolve().parent
EXP = ["--iterations", "2", "--cycle", "0.15", "--disturbance", "both", "--seed", "3"]
EXP_CFG = {"iterations": 2, "cycle_s": 0.15, "disturbance": "both", "seed": 3}


def test_non_loopback_hub_address_needs_the_explicit_opt_in() -> None:
    with pytest.raises(NonLoopbackAddressError, match="--allow-remote"):
        parse_address("tcp:10.212.0.1:29541")
    with pytest.raises(NonLoopbackAddressError):
        HubServer(["tcp:10.212.0.1:0"])
    with pytest.raises(NonLoopbackAddressError):
        hub_transport("tcp:10.212.0.1:29541")
    with pytest.raises(NonLoopbackAddressError, match="wildcard"):
        parse_address("tcp:0.0.0.0:29541", allow_remote=True)
    assert parse_address("tcp:10.212.0.1:29541", allow_remote=True).host == "10.212.0.1"
    tc = hub_transport("tcp:10.212.0.1:29541", allow_remote=True)
    assert tc.fieldbus.kwargs == {"allow_remote": True}


def _two_netns_reason() -> str | None:
    reason = netns_unavailable_reason()
    if reason:
        return reason
    if shutil.which("nsenter") is None:
        return "nsenter(1) not installed"
    probe = (
        "ip link set lo up && unshare -n sh -c 'echo $$; exec sleep 5' > /tmp/.ilcrig-ns-$$ & sleep 0.3; "
        "p=$(head -1 /tmp/.ilcrig-ns-$$); rm -f /tmp/.ilcrig-ns-$$; "
        "ip link add vt-a type veth peer name vt-b netns $p && nsenter -t $p -n ip link show vt-b >/dev/null"
    )
    res = subprocess.run(["unshare", "-rn", "sh", "-c", probe], capture_output=True, text=True, timeout=30)
    if res.returncode != 0:
        return f"nested network namespaces with a veth pair unavailable: {res.stderr.strip()[-300:]}"
    return None


@pytest.mark.netns
@pytest.mark.multiprocess
@pytest.mark.slow
def test_roles_in_two_namespaces_joined_by_a_veth_pair_equal_sim(tmp_path: Path) -> None:
    reason = _two_netns_reason()
    if reason:
        pytest.skip(reason)
    cmd = ["unshare", "-rn", sys.executable, str(HERE / "two_netns_rig.py"), str(tmp_path), *EXP]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=600)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
    logs = "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-1500:]}" for p in sorted(tmp_path.glob("*.log")))
    assert proc.returncode == 0, out + err + logs
    res = json.loads(out.strip().splitlines()[-1])
    assert res["host_rc"] == 0, logs
    cfg = build_config(None, EXP_CFG)
    assert res["digest"] == run_experiment(prepare(cfg), InProcessBench(cfg), None, mode="sim").summary["trace_sha256"]
    # B is a separate "machine": only its loopback and its end of the pair; the hub is not on its loopback
    assert res["b_interfaces"] == ["lo", "veth-b"] and res["a_interfaces"] == ["lo", "veth-a"]
    assert res["b_reaches_hub_on_loopback"] is False

"""Run by tests/test_two_netns.py inside ``unshare -rn`` (network namespace A, in a user namespace
the test made): roles on two "machines" joined by a veth pair.

A second network namespace B is created inside the same user namespace; a veth pair joins A and
B, with private addresses on that pair only (HUB_IP in A, PEER_IP in B, a /30).  Nothing else is
configured and no other interface is touched: both namespaces, the pair and every process die
with this script.  A runs the hub (``--allow-remote``, listening on HUB_IP only) and the four
drives; B (entered with nsenter) runs the plant and the host, which reach the hub over the veth.
The script prints one JSON line: the host's exit code, its summary's digest, B's interfaces and
whether B could reach A's loopback.

Usage: ``python two_netns_rig.py OUT_DIR EXPERIMENT_OPTIONS...``
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

HUB_IP = "10.212.0.1"
PEER_IP = "10.212.0.2"
PORT = 29541
REPO = Path(__file__).resolve().parent.parent


def sh(*cmd: str) -> None:
    subprocess.run(cmd, check=True)


def main() -> int:
    out = Path(sys.argv[1])
    exp = sys.argv[2:]
    out.mkdir(parents=True, exist_ok=True)
    sh("ip", "link", "set", "lo", "up")
    # namespace B: a process that lives until our stdin pipe to it closes
    holder = subprocess.Popen(
        ["unshare", "-n", "sh", "-c", "echo $$; exec cat"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert holder.stdout is not None
    pid_b = holder.stdout.readline().strip()
    procs: list[subprocess.Popen[bytes]] = []
    result: dict[str, object] = {}
    try:
        sh("ip", "link", "add", "veth-a", "type", "veth", "peer", "name", "veth-b", "netns", pid_b)
        sh("ip", "addr", "add", f"{HUB_IP}/30", "dev", "veth-a")
        sh("ip", "link", "set", "veth-a", "up")
        in_b = ["nsenter", "-t", pid_b, "-n"]
        sh(*in_b, "sh", "-c", f"ip link set lo up && ip addr add {PEER_IP}/30 dev veth-b && ip link set veth-b up")
        hub_addr = f"tcp:{HUB_IP}:{PORT}"
        env = dict(os.environ)

        def start(argv: list[str], log: str, prefix: list[str] | None = None) -> subprocess.Popen[bytes]:
            fh = open(out / log, "wb")  # noqa: SIM115 - the child keeps its own descriptor
            try:
                p = subprocess.Popen(
                    [*(prefix or []), sys.executable, *argv],
                    cwd=REPO,
                    stdout=fh,
                    stderr=subprocess.STDOUT,
                    env=env,
                    start_new_session=True,
                )
            finally:
                fh.close()
            procs.append(p)
            return p

        hub = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "host.cli",
                "hub",
                "--listen",
                hub_addr,
                "--allow-remote",
                "--ready",
                "--log-level",
                "WARNING",
            ],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
        procs.append(hub)  # type: ignore[arg-type]
        assert hub.stdout is not None
        ready = hub.stdout.readline().decode()
        if not ready.startswith("ILCRIG-HUB-READY") and "READY" not in ready:
            raise RuntimeError(f"hub did not start: {ready!r}")
        bus = ["--bus", "hub", "--hub", hub_addr, "--allow-remote"]
        for node in (1, 2, 3, 4):
            start(["-m", "host.cli", "drive", "--node", str(node), *bus], f"drive{node}.log")
        start(["-m", "host.cli", "plant", *bus], "plant.log", in_b)
        host = start(["-m", "host.cli", "host", *exp, *bus, "--out", str(out / "run"), "--wait", "120"], "host.log", in_b)
        try:
            rc = host.wait(timeout=500)
        except subprocess.TimeoutExpired:
            rc = -999
        result["host_rc"] = rc
        summary = out / "run" / "summary.json"
        result["digest"] = json.loads(summary.read_text())["trace_sha256"] if summary.exists() else None
        probe = (
            f"import socket,json;s=socket.socket();s.settimeout(2);r=s.connect_ex(('127.0.0.1',{PORT}));"
            "print(json.dumps([[n for _,n in socket.if_nameindex()], r]))"
        )
        names, loop_rc = json.loads(
            subprocess.run([*in_b, sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
        )
        result["b_interfaces"] = sorted(names)
        result["b_reaches_hub_on_loopback"] = loop_rc == 0
        result["a_interfaces"] = sorted(n for _, n in socket.if_nameindex())
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        deadline = time.monotonic() + 10
        for p in procs:
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        assert holder.stdin is not None
        holder.stdin.close()
        holder.wait(10)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

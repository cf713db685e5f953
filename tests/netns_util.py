"""Test helper: run a Python script inside a private user+network namespace (``unshare -rn``).

Inside, loopback is brought up with multicast and a 224.0.0.0/4 route (docs/architecture.md §6, "Rules of
this environment"), so udp_multicast traffic never reaches a real interface.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

NETNS_SETUP = "ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo"


@functools.cache
def netns_unavailable_reason() -> str | None:
    """``None`` if ``unshare -rn`` + the loopback setup work here, else why not."""
    if shutil.which("unshare") is None:
        return "unshare(1) not installed"
    if shutil.which("ip") is None:
        return "ip(8) not installed"
    try:
        res = subprocess.run(["unshare", "-rn", "sh", "-c", NETNS_SETUP], capture_output=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired) as err:
        return f"unshare -rn failed: {err}"
    if res.returncode != 0:
        return f"unprivileged user+network namespaces unavailable: {res.stderr.decode().strip()}"
    return None


def run_in_netns(script: Path, *args: str, timeout_s: float = 30.0) -> subprocess.CompletedProcess[str]:
    """Run ``python script args…`` in a fresh private netns; kill its whole process group on timeout."""
    cmd = ["unshare", "-rn", "sh", "-c", f'{NETNS_SETUP} && exec "$0" "$@"', sys.executable, str(script), *args]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True, env=dict(os.environ)
    )
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def script_report_in_netns(folder: Path, name: str, text: str, timeout_s: float) -> Any:
    """The script ``text`` (saved as ``folder/name``) run in a private netns (the test skipped where
    there is none); it must exit 0, and its last stdout line, JSON, is returned."""
    reason = netns_unavailable_reason()
    if reason:
        pytest.skip(reason)
    script = folder / name
    script.write_text(text)
    res = run_in_netns(script, timeout_s=timeout_s)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1])

"""The same master sequence gives the same trace whatever the machine's load (docs/robot.md "Time").

``scripts/robot-soak`` runs the issue's streaming master (tests/streaming_master.py: map, start, 30
SYNCs, enable by SDO one SYNC per step, then RPDO1 + SYNC every 2–5 ms up to 565 SYNCs) against a
fresh ``ilcrig robot``: once on the machine as it is, then twice beside two CPU hogs the script
starts and stops itself.  Every run steps every SYNC (565 SYNCs → 565 periods) and gives the idle
run's trace digest.  The 20-run soak is a benchmark (docs/benchmarks.md).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

# alone: its idle run is the machine as it is, its loaded runs beside hogs of its own (pyproject.toml)
pytestmark = [pytest.mark.slow, pytest.mark.multiprocess, pytest.mark.alone]

REPO = Path(__file__).resolve().parents[1]
SOAK = REPO / "scripts" / "robot-soak"


def soak(*args: str) -> tuple[int, dict]:
    done = subprocess.run([sys.executable, str(SOAK), "--json", *args], cwd=REPO, capture_output=True, text=True, timeout=1800)
    assert done.stdout, done.stderr
    return done.returncode, json.loads(done.stdout[done.stdout.index("{") :])


def test_the_master_sequence_gives_the_idle_digest_beside_two_cpu_hogs() -> None:
    code, idle = soak("--runs", "1", "--hogs", "0")
    assert code == 0 and idle["every_sync_a_period"], idle
    (digest,) = idle["digests"]
    assert idle["results"][0]["periods"] == 565
    code, loaded = soak("--runs", "2", "--hogs", "2", "--expect", digest)
    assert loaded["every_sync_a_period"] and loaded["digests"] == [digest], loaded
    assert code == 0

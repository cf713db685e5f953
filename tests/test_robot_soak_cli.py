"""``scripts/robot-soak``'s options (fast tier; the soak itself is tests/test_robot_soak.py): ``--expect``
takes a digest as the docs print it (its first 16 hex digits) or whole, and refuses anything else in
one line naming the option, exit code 2, before any robot starts."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SOAK = REPO / "scripts" / "robot-soak"


def soak(*args: str) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, str(SOAK), "--runs", "0", "--hogs", "0", *args]
    return subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=120)


def test_a_digest_that_is_not_one_is_refused_naming_the_option() -> None:
    done = soak("--expect", "8eabb5ec")
    assert done.returncode == 2 and not done.stdout
    lines = done.stderr.strip().splitlines()
    assert lines[-1] == "robot-soak: error: argument --expect: '8eabb5ec' is not a trace digest: 16 to 64 hex digits"


def test_a_digest_as_the_docs_print_it_is_taken() -> None:
    done = soak("--expect", "1346D2A4C944B44A…", "--json")  # no run: nothing to compare, so not ok
    verdict = json.loads(done.stdout)
    assert done.returncode == 1 and verdict["runs"] == 0 and verdict["expected_digest"] is False

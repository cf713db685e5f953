"""Long trials: a 20 s trial (N = 20,001) runs in ``ilcrig sim`` within a 2 GB address-space
limit, the longest trial the drives' tables hold (N = 59,999) runs, and the measured peak memory
of both stays within the preflight's estimate (:func:`host.experiment.plan.run_memory_bytes`),
which is what refuses a run that would not fit."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bus.objects import TABLE_CAPACITY
from host.experiment import plan as plan_mod
from host.experiment.config import build_config

ROOT = Path(__file__).resolve().parent.parent
#: the address-space limit of the 20 s trial, bytes.  ``ilcrig sim --cycle 10 --iterations 2``
#: needs about 1.8 GB of it; unconstrained its virtual size is 3.7 GB, of which two 1 GiB arenas
#: that rerun's allocator (mimalloc) reserves and ten 64 MiB per-thread arenas of glibc: reservations
#: that shrink to what is there under a limit.  The longest trial runs without a limit: it needs
#: about 2.8 GB of address space, as mimalloc reserves its second arena before the report is drawn
#: (with ``MIMALLOC_ARENA_RESERVE=64MiB`` it runs within 2 GB).  Under the limit the allocators'
#: reservations are kept small (:data:`SMALL_RESERVATIONS`): they count against an address-space
#: limit but are not memory a machine must have, and how many glibc arenas the threads of a run
#: happen to create varied enough to leave one run without room to map matplotlib's library.
ADDRESS_SPACE_BYTES = 2 * 1000**3
#: the allocators' reservations under the limit: mimalloc's arenas 64 MiB, two glibc arenas
SMALL_RESERVATIONS = {"MIMALLOC_ARENA_RESERVE": "64MiB", "MALLOC_ARENA_MAX": "2"}


def _limit_address_space() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE_BYTES, ADDRESS_SPACE_BYTES))


def run_sim(tmp_path: Path, *argv: str, limit_address_space: bool, timeout_s: float = 600.0) -> tuple[int, str, str, int]:
    """``ilcrig sim ARGV --out tmp_path/run`` in a child (under :data:`ADDRESS_SPACE_BYTES` if
    ``limit_address_space``): (exit code, stdout, stderr, the child's own peak resident memory in
    bytes, from ``wait4``)."""
    with open(tmp_path / "stdout", "w+") as out, open(tmp_path / "stderr", "w+") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "host.cli", "sim", *argv, "--out", str(tmp_path / "run")],
            stdout=out,
            stderr=err,
            cwd=ROOT,
            preexec_fn=_limit_address_space if limit_address_space else None,
            env={**os.environ, **SMALL_RESERVATIONS} if limit_address_space else None,
        )
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
                if pid:
                    break
                if time.monotonic() > deadline:
                    raise AssertionError(f"ilcrig sim {' '.join(argv)} still running after {timeout_s:.0f} s")
                time.sleep(0.1)
        finally:
            if not pid:
                proc.kill()
                os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        return proc.returncode, out.read(), err.read(), usage.ru_maxrss * 1024


@pytest.mark.slow
@pytest.mark.parametrize(
    ("cycle", "law", "n", "limit_address_space"),
    [("10", "no-ilc-id", 20001, True), ("29.999", "pd-ilc", 59999, False)],
    ids=["20s-default-law-2GB-address-space", "longest-table-pd-ilc"],
)
def test_a_long_trial_runs_within_its_memory_estimate(
    tmp_path: Path, cycle: str, law: str, n: int, limit_address_space: bool
) -> None:
    code, out, err, peak = run_sim(
        tmp_path, "--cycle", cycle, "--law", law, "--iterations", "2", limit_address_space=limit_address_space
    )
    assert code == 0, err
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["completed"] is True and s["faults"] == []
    assert s["ticks"] == 2 * n
    assert [it["k"] for it in s["iterations"]] == [0, 1]
    assert f"N = {n} ticks/trial" in out
    last = out.strip().splitlines()[-1]
    assert last.startswith(f"{2 * n} ticks in ") and f"trace_sha256 {s['trace_sha256'][:16]}…" in last
    # the preflight's estimate covers what the run took, and is not far above it
    estimate = plan_mod.run_memory_bytes(n, 2, law)
    assert peak <= estimate <= 2 * peak, (peak, estimate)


def test_the_trial_length_stays_limited_by_the_drives_tables() -> None:
    assert plan_mod.check_config_limits(build_config(None, {"cycle_s": 29.999, "iterations": 1})) == TABLE_CAPACITY - 1
    with pytest.raises(plan_mod.PlanError, match=r"N = 60001 samples exceeds the drives' table capacity of 60000"):
        plan_mod.check_config_limits(build_config(None, {"cycle_s": 30.0}))


def test_the_longest_run_fits_this_machine_only_if_the_estimate_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    """The largest run the options allow (N = 59,999, 1000 trials) is refused exactly when its
    estimate exceeds the available memory: at one byte less than the estimate, and not at it."""
    cfg = build_config(None, {"cycle_s": 29.999, "iterations": 1000})
    need = plan_mod.run_memory_bytes(59999, 1000, cfg.law)
    monkeypatch.setenv(plan_mod.MEMORY_ENV, str(need))
    assert plan_mod.check_config_limits(cfg) == 59999
    monkeypatch.setenv(plan_mod.MEMORY_ENV, str(need - 1))
    with pytest.raises(plan_mod.PlanError, match=rf"needs about {need / 1024**3:.1f} GiB of memory"):
        plan_mod.check_config_limits(cfg)

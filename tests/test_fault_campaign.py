"""The fast subset of the seeded fault campaign (benchmarks/fault_campaign.py): five runs of real
``ilcrig run`` rigs — our own SIGKILL / SIGSTOP of a process at a moment read off the run's stdout,
and ``--inject`` specs — each checked against the campaign's invariants: a summary exists (a
SIGKILL of the launcher aside), no printed trial lost, no silent stall or injection, the fault
record names what was done where it was done, no null detection time, nothing left.

The runs are the campaign's own (seed 33, the first five): the same draw as the benchmark's table
in docs/benchmarks.md. Multi-process and timing-sensitive: full tier only.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import fault_campaign  # noqa: E402

pytestmark = [pytest.mark.faultmatrix, pytest.mark.multiprocess, pytest.mark.slow]

ITERATIONS = 2
PLANS = fault_campaign.plans(5, 33, ITERATIONS, round(2 * 0.15 / 0.001) + 1)


@pytest.mark.parametrize("plan", PLANS, ids=[f"{p.i}-{p.spec.replace(' ', '-')}-{p.moment}" for p in PLANS])
def test_campaign_run_keeps_the_invariants(tmp_path: Path, plan: fault_campaign.Plan) -> None:
    result = fault_campaign.run_one(plan, tmp_path, ITERATIONS)
    assert set(result["bad"]) <= set(fault_campaign.APART), result

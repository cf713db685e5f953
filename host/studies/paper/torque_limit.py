"""The torque-limit section of the sweep report: where the unconstrained laws reach the drives' joint
torque limit and what the constrained law (``cno-ilc``) does there.

This module owns :func:`torque_limit_section` (markdown lines).  Per experiment of
:func:`host.studies.paper.plan.limit_experiments` (the laws of :data:`LIMIT_LAWS` at
:data:`LIMIT_CYCLE_S` and at 0.15 s, the paper's Table 5 row): the peak total torque the drives
applied over the learned trials (k ≥ 1; trial 0 plays the same initial feed-forward for every law),
how many of those trials reached the limit (the drive clamps there: ≥ 99.9 % of it), the final mean
RMSE, and the verdict "the constrained law keeps every learned trial below the limit".
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from host.studies.paper.plan import LIMIT_CYCLE_S, Experiment, RunData, limit_experiments
from plant.params import default_true_plant

logger = logging.getLogger(__name__)

__all__ = ["torque_limit_section", "AT_LIMIT_FRACTION"]

#: a trial "reached the limit" when a joint's peak total torque is at least this fraction of it
AT_LIMIT_FRACTION = 0.999


def torque_limit_section(get: Callable[[Experiment], RunData | None]) -> list[str]:
    """The section's markdown lines for the finished runs ``get`` returns."""
    limit = float(default_true_plant().joint_torque_limit_nm)
    lines = [f"## Beyond the paper — the joint torque limit ({limit:g} N·m)", ""]
    rows, at_limit = [], {}
    for exp in limit_experiments():
        run = get(exp)
        if run is None:
            continue
        its = run.summary["iterations"]
        learned = [it for it in its[1:] if it.get("role", "learning") == "learning"]
        peaks = np.array([it["peak_torque_nm"] for it in learned], dtype=float).reshape(-1, 4)
        hits = int(np.sum(np.max(peaks, axis=1) >= AT_LIMIT_FRACTION * limit)) if peaks.size else 0
        at_limit[(exp.law, exp.cycle_s)] = hits
        final = float(np.mean(run.metric("rmse_deg")[-1])) if its else float("nan")
        rows.append(
            f"| {exp.law} | {exp.cycle_s:g} s | {float(peaks.max()) if peaks.size else float('nan'):.1f} | "
            f"{hits} of {len(learned)} | {final:.3g} |"
        )
    if not rows:
        return lines + ["not run in this sweep folder (`--only beyond`)", ""]
    lines += [
        f"4-5-6-7 law, path 1. At {LIMIT_CYCLE_S:g} s the emulated robot (1.7–2× the nominal inertia) needs more "
        "than the limit while the nominal model passes the feasibility check; at 0.15 s (the paper's Table 5 "
        "row) the peaks stay near 200 N·m and no law reaches the limit. *peak* = the largest total torque the "
        "drives applied in the learned trials (k ≥ 1), N·m; *at the limit* = learned trials in which a joint "
        f"reached ≥ {AT_LIMIT_FRACTION:.1%} of it (the drive clamps there); *final* = mean RMSE over joints "
        "of the last trial, deg.",
        "",
        "| law | cycle | peak N·m | at the limit | final RMSE |",
        "|---|---|---|---|---|",
        *rows,
        "",
    ]
    cons = at_limit.get(("cno-ilc", LIMIT_CYCLE_S))
    if cons is not None:
        word = "holds" if cons == 0 else "does not hold"
        lines += [
            f"Verdict: the constrained law keeps every learned trial below the limit at {LIMIT_CYCLE_S:g} s — **{word}**.",
            "",
        ]
    logger.debug("torque-limit section: %d runs", len(rows))
    return lines

"""The verdict rules of the sweep report on RMSE histories (pure functions): how fast a law
settles, whether its RMSE rises on the way, the floor under a disturbance, and whether a long run
stays settled.

The definitions (settle iteration, floor, block windows) are :mod:`host.studies.settling`;
every verdict states the criterion it was judged by (:attr:`~host.studies.paper.verdicts.Verdict.criterion`).
RMSE histories are (K, J) arrays in deg, k = 0 the first trial, before any learning.
"""

from __future__ import annotations

import logging

import numpy as np

from host.analysis.markdown import fmt
from host.studies.paper.paper_data import PAPER_SETTLE_ITERATIONS
from host.studies.paper.verdicts import Verdict, jlist, verdict_floor_raised
from host.studies.settling import (
    SETTLE_FACTOR,
    SPLIT_TRIALS,
    block_means,
    history,
    settle_iterations,
    settled_floor,
    settled_windows,
)

logger = logging.getLogger(__name__)

__all__ = [
    "verdict_settle",
    "verdict_rise",
    "verdict_disturbance",
    "verdict_long_bounded",
    "SETTLE_LIMIT",
    "GROWTH_LIMIT",
    "LONG_BLOCK",
    "LONG_GROWTH_LIMIT",
    "RISE_TOLERANCE",
    "CRITERION_SETTLE_ITERATION",
    "CRITERION_FLOOR",
    "CRITERION_RISE",
    "criterion_settle",
    "criterion_disturbance",
    "criterion_long",
]

#: "about 4 iterations": settled at k ≤ 4 + 1
SETTLE_LIMIT = PAPER_SETTLE_ITERATIONS + 1
#: bounded under disturbance: the last-L mean RMSE at most this factor above the L trials before
GROWTH_LIMIT = 1.5
#: long-run stability: the last LONG_BLOCK-trial mean RMSE at most LONG_GROWTH_LIMIT× the best
#: block mean after settling
LONG_BLOCK = 20
LONG_GROWTH_LIMIT = 2.0
#: a rise in an RMSE sequence counts when larger than this relative step
RISE_TOLERANCE = 0.01

#: the settle iteration in words (used by the verdicts and the report's definitions)
CRITERION_SETTLE_ITERATION = (
    f"settle iteration = the first trial k (k = 0: before learning) from which every joint's RMSE stays within "
    f"{SETTLE_FACTOR:g}× of its final (last-trial) RMSE, above and below"
)
#: the floor in words
CRITERION_FLOOR = (
    "floor = the mean RMSE per joint over the trials from the settle iteration on; a run with disturbance "
    "takes the settle iteration of its run without disturbance (one disturbed trial scatters by more than "
    f"{SETTLE_FACTOR:g}×)"
)


def criterion_settle(limit: int = SETTLE_LIMIT) -> str:
    """The rule of :func:`verdict_settle` in words."""
    return f"{CRITERION_SETTLE_ITERATION}; 'within about {PAPER_SETTLE_ITERATIONS} iterations' = a settle iteration k ≤ {limit}"


#: the rule of :func:`verdict_rise` in words
CRITERION_RISE = f"some joint's RMSE exceeds its value in the trial before by more than {RISE_TOLERANCE:.0%}"


def criterion_disturbance(last: int = SPLIT_TRIALS) -> str:
    """The rule of :func:`verdict_disturbance` in words (``last`` trials compared with as many before)."""
    return (
        f"{CRITERION_FLOOR}; {CRITERION_SETTLE_ITERATION}; raised = the floor with disturbance larger than without on every "
        f"joint; bounded = every learnt trial (k ≥ 1) below the first and the mean RMSE of the last {last} "
        f"trials at most {GROWTH_LIMIT:g}× the mean of the {last} before"
    )


def criterion_long(block: int = LONG_BLOCK, limit: float = LONG_GROWTH_LIMIT) -> str:
    """The rule of :func:`verdict_long_bounded` in words."""
    return (
        f"{CRITERION_SETTLE_ITERATION}, over the paper's horizon (the first trials, as many as the short runs; a disturbed run "
        f"takes the one of its run without disturbance); bounded = the mean RMSE over joints of the last {block} "
        f"trials at most {fmt(limit, 2)}× the best {block}-trial mean after settling"
    )


def verdict_settle(rmse_hist: np.ndarray, limit: int = SETTLE_LIMIT, law: str = "PD-ILC", claim: str | None = None) -> Verdict:
    """Every joint settles (:func:`~host.studies.settling.settle_iteration`) at k ≤ ``limit``."""
    claim = claim or f"{law} errors settle within about {PAPER_SETTLE_ITERATIONS} iterations (k ≤ {limit})"
    crit = criterion_settle(limit)
    if len(rmse_hist) < 2:
        return Verdict(claim, None, "needs at least 2 trials", crit)
    h = history(rmse_hist)
    ks = settle_iterations(h)
    txt = f"settles at k = {max(ks)} ({', '.join(f'j{j + 1} {k}' for j, k in enumerate(ks))}; of {h.shape[0]} trials)"
    if h.shape[0] <= limit + 1:
        return Verdict(claim, None, f"too few trials to judge ({h.shape[0]}); {txt}", crit)
    late = [j for j, k in enumerate(ks) if k > limit]
    if not late:
        return Verdict(claim, True, txt, crit)
    at = ", ".join(
        f"j{j + 1} {fmt(h[limit, j])} ({fmt(h[limit, j] / h[-1, j], 2)}× the final {fmt(h[-1, j])})"
        if h[-1, j] > 0
        else f"j{j + 1} {fmt(h[limit, j])} (final 0)"
        for j in late
    )
    return Verdict(claim, False, f"{jlist(late)} not settled at k = {limit}: RMSE there {at} deg; {txt}", crit)


def verdict_rise(rmse_hist: np.ndarray, law: str = "D-ILC", claim: str | None = None) -> Verdict:
    """Some joint's RMSE increases from one trial to the next (by more than RISE_TOLERANCE)."""
    claim = claim or f"{law}'s RMSE increases at some point during convergence"
    crit = CRITERION_RISE
    if len(rmse_hist) < 2:
        return Verdict(claim, None, "needs at least 2 trials", crit)
    h = history(rmse_hist)
    rises = [(k, j) for k in range(1, h.shape[0]) for j in range(h.shape[1]) if h[k, j] > h[k - 1, j] * (1 + RISE_TOLERANCE)]
    if rises:
        k, j = rises[0]
        return Verdict(
            claim,
            True,
            f"first rise at k = {k} on j{j + 1} ({fmt(h[k - 1, j])} → {fmt(h[k, j])} deg); {len(rises)} rise(s) in all",
            crit,
        )
    return Verdict(
        claim,
        False,
        f"the RMSE of every joint decreases monotonically over all {h.shape[0]} trials "
        f"here (a D-type law with a one-sample lead on this plant does not overshoot)",
        crit,
    )


def verdict_disturbance(
    rmse_none: np.ndarray, rmse_dist: np.ndarray, last: int = SPLIT_TRIALS, law: str = "PD-ILC", claim: str | None = None
) -> Verdict:
    """Floor raised and bounded: the floor (mean RMSE from the settle iteration of the run without
    disturbance on, for both runs) with disturbance larger than without on every joint; every
    learnt trial (k ≥ 1) below trial 0, and the mean of the last L trials at most GROWTH_LIMIT×
    the L before."""
    claim = claim or f"with {law}, a disturbance raises the error floor but the error stays bounded"
    n = min(last, len(rmse_dist) // 2)
    crit = criterion_disturbance(max(n, 1))
    if n < 1 or len(rmse_none) < 1:
        return Verdict(
            claim, None, f"needs a trial without and 2 with disturbance (have {len(rmse_none)}, {len(rmse_dist)})", crit
        )
    hn, hd = history(rmse_none), history(rmse_dist)
    fn = settled_floor(hn)
    fd = settled_floor(hd, settle=fn.settle)
    raised = verdict_floor_raised(fn.floor_deg, fd.floor_deg)
    above0 = [j for j in range(hd.shape[1]) if np.any(hd[1:, j] >= hd[0, j])]
    growth = hd[-n:].mean(axis=0) / hd[-2 * n : -n].mean(axis=0)
    grows = [j for j in range(hd.shape[1]) if growth[j] > GROWTH_LIMIT]
    btxt = f"growth of the last {n} trials over the {n} before: " + ", ".join(
        f"j{j + 1} {fmt(growth[j], 2)}×" for j in range(len(growth))
    )
    where = f"settle iteration {fn.settle}: floors over k = {fn.settle}..{hn.shape[0] - 1}" + (
        " (settled only in the last trial: an upper bound)" if fn.trials == 1 else ""
    )
    problems = []
    if not raised.holds:
        problems.append(raised.detail)
    if above0:
        problems.append(f"unbounded: a learnt trial is no better than the first on {jlist(above0)}")
    if grows:
        problems.append(f"unbounded: the error grows on {jlist(grows)} ({btxt})")
    if problems:
        return Verdict(claim, False, "; ".join(problems) + f" ({where})", crit)
    return Verdict(claim, True, f"{raised.detail} ({where}); bounded, {btxt}", crit)


def verdict_long_bounded(
    rmse_hist: np.ndarray,
    settle: int,
    block: int = LONG_BLOCK,
    limit: float = LONG_GROWTH_LIMIT,
    claim: str = "the error stays bounded over a long run",
) -> Verdict:
    """Long-run stability: the mean RMSE over joints of the last ``block`` trials is at most
    ``limit``× the best ``block``-trial mean starting at the settle iteration or later.

    :param settle: the settle iteration over the paper's horizon (of the same experiment without
        disturbance for a disturbed run; :mod:`host.studies.settling`)
    """
    crit = criterion_long(block, limit)
    if len(rmse_hist) < 2 * block:
        return Verdict(claim, None, f"needs at least {2 * block} trials (have {len(rmse_hist)})", crit)
    h = history(rmse_hist)
    k_total = h.shape[0]
    w = settled_windows(h, block, settle)
    if w.best_start is None:
        return Verdict(claim, None, f"needs {block} trials after the settle iteration k = {settle} (have {k_total})", crit)
    growth = w.last_mean_deg / w.best_mean_deg if w.best_mean_deg > 0 else float("inf")
    txt = (
        f"settle iteration k = {w.settle}; mean RMSE over joints: best {block} trials after settling "
        f"k = {w.best_start}..{w.best_start + block - 1} {fmt(w.best_mean_deg)} deg, last {block} trials "
        f"{fmt(w.last_mean_deg)} deg ({fmt(growth, 3)}× the best) over {k_total} trials"
    )
    if growth <= limit:
        return Verdict(claim, True, txt, crit)
    means = block_means(h.mean(axis=1), block)
    first = int(np.argmax(means[w.best_start :] > limit * w.best_mean_deg)) + w.best_start
    return Verdict(
        claim,
        False,
        f"the error grows again: the {block}-trial mean exceeds {fmt(limit, 2)}× the best after settling from the "
        f"window k = {first}..{first + block - 1} on; {txt}",
        crit,
    )

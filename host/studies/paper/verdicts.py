"""The verdict rules of the sweep report that compare errors after learning (pure functions).

Owns :class:`Verdict` (a claim, whether it holds, the numbers and the criterion it was judged by)
and the rules on the errors after learning — the last trial of a run, as the paper's tables give
them; MaxE = max |e|, "mean error" = MAE = mean |e| (the paper's eq. 36), deg, joints 1–4:
:func:`verdict_beats` (Table 2), :func:`verdict_floor_raised` (Table 3 on the paper's numbers),
:func:`verdict_paths` (Table 4), :func:`verdict_cycles` (Table 5), :func:`verdict_profiles_similar`
and :func:`verdict_profiles_order` (Table 6).  The rules on RMSE histories (settling, floors, long
runs) are :mod:`host.studies.paper.convergence_verdicts`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from host.analysis.markdown import Floats, fmt

logger = logging.getLogger(__name__)

__all__ = [
    "Verdict",
    "jlist",
    "missing",
    "verdict_beats",
    "verdict_floor_raised",
    "verdict_paths",
    "verdict_cycles",
    "verdict_profiles_similar",
    "verdict_profiles_order",
    "PATH_SPREAD_LIMIT",
    "PROFILE_RATIO_LIMIT",
    "TIE_FRACTION",
    "criterion_beats",
    "criterion_paths",
    "criterion_profiles_similar",
    "CRITERION_FLOOR_RAISED",
    "CRITERION_CYCLES",
    "CRITERION_PROFILES_ORDER",
]

#: paths "similar": worst-joint error spread across paths at most this factor (paper: 1.4 / 1.7)
PATH_SPREAD_LIMIT = 2.0
#: motion laws "as good": worst-joint errors within this factor (paper: 1.04)
PROFILE_RATIO_LIMIT = 1.5
#: strict orderings that fail by less than this relative margin are flagged as ties
TIE_FRACTION = 0.05


@dataclass(frozen=True)
class Verdict:
    """A claim judged on runs: ``holds`` (None = not evaluated, experiments missing), the numbers
    behind it (``detail``) and the rule it was judged by (``criterion``)."""

    claim: str
    holds: bool | None
    detail: str
    criterion: str = ""

    @property
    def word(self) -> str:
        return {True: "holds", False: "does not hold", None: "not evaluated"}[self.holds]

    def line(self) -> str:
        """The verdict as a markdown list item, its criterion beside it."""
        crit = f" *Criterion:* {self.criterion}." if self.criterion else ""
        if self.holds is None:
            return f"- **not evaluated** — {self.claim}: {self.detail}{crit}"
        joiner = "" if self.holds else "reason: "
        return f"- **{self.word}** — {self.claim}. {joiner}{self.detail}.{crit}"


def missing(claim: str, what: str, criterion: str = "") -> Verdict:
    """The verdict of a claim whose experiments are not in the sweep folder."""
    return Verdict(claim, None, f"experiments not run ({what})", criterion)


def criterion_beats(a: str = "PD-ILC", b: str = "D-ILC") -> str:
    """The rule of :func:`verdict_beats` in words."""
    return f"{a}'s MaxE and mean error after learning are both smaller than {b}'s on every joint"


#: the rule of :func:`verdict_floor_raised` in words
CRITERION_FLOOR_RAISED = "the floor with disturbance is larger than the floor without on every joint"
#: the rule of :func:`verdict_cycles` in words
CRITERION_CYCLES = (
    "MaxE and mean error after learning strictly decrease with the cycle time on every joint "
    f"(a failure where every violation is within {TIE_FRACTION:.0%} is flagged as a tie)"
)
#: the rule of :func:`verdict_profiles_order` in words
CRITERION_PROFILES_ORDER = (
    "the 4-5-6-7 law's mean error after learning is smaller than the 5th-order law's on every joint "
    f"(a failure where every difference is within {TIE_FRACTION:.0%} is flagged as a tie)"
)


def criterion_paths(limit: float = PATH_SPREAD_LIMIT) -> str:
    """The rule of :func:`verdict_paths` in words."""
    return (
        f"the worst-joint MaxE and the worst-joint mean error after learning differ across the paths by at most {fmt(limit, 2)}×"
    )


def criterion_profiles_similar(limit: float = PROFILE_RATIO_LIMIT) -> str:
    """The rule of :func:`verdict_profiles_similar` in words."""
    return f"the worst-joint MaxE and the worst-joint mean error after learning of the two motion laws within {fmt(limit, 2)}×"


def verdict_beats(
    a_maxe: Floats, a_mae: Floats, b_maxe: Floats, b_mae: Floats, a: str = "PD-ILC", b: str = "D-ILC", claim: str | None = None
) -> Verdict:
    """``a`` beats ``b``: smaller MaxE and smaller MAE on every joint."""
    claim = claim or f"{a} gives smaller MaxE and mean error than {b} on every joint"
    crit = criterion_beats(a, b)
    am, aa, bm, ba = (np.asarray(x, float) for x in (a_maxe, a_mae, b_maxe, b_mae))
    worse_max = [j for j in range(len(am)) if not am[j] < bm[j]]
    worse_mae = [j for j in range(len(aa)) if not aa[j] < ba[j]]
    ratio = ", ".join(f"j{j + 1} {fmt(ba[j] / aa[j], 2)}×" if aa[j] > 0 else f"j{j + 1} ∞" for j in range(len(aa)))
    if not worse_max and not worse_mae:
        return Verdict(claim, True, f"{b}/{a} mean-error ratio: {ratio}", crit)
    parts = []
    if worse_max:
        parts.append(
            f"MaxE of {a} not smaller on {jlist(worse_max)} ("
            + ", ".join(f"{fmt(am[j])} vs {fmt(bm[j])}" for j in worse_max)
            + " deg)"
        )
    if worse_mae:
        parts.append(
            f"mean error of {a} not smaller on {jlist(worse_mae)} ("
            + ", ".join(f"{fmt(aa[j])} vs {fmt(ba[j])}" for j in worse_mae)
            + " deg)"
        )
    return Verdict(claim, False, "; ".join(parts), crit)


def verdict_floor_raised(
    floor_none: Floats,
    floor_dist: Floats,
    claim: str = "a disturbance raises the error floor on every joint",
    criterion: str = CRITERION_FLOOR_RAISED,
) -> Verdict:
    """The floor with disturbance is larger than without on every joint."""
    a, b = np.asarray(floor_none, float), np.asarray(floor_dist, float)
    low = [j for j in range(len(a)) if not b[j] > a[j]]
    txt = ", ".join(f"j{j + 1} {fmt(a[j])} → {fmt(b[j])}" for j in range(len(a)))
    if not low:
        return Verdict(claim, True, f"floor without → with disturbance: {txt} deg", criterion)
    return Verdict(claim, False, f"not raised on {jlist(low)}: {txt} deg", criterion)


def _spread(values: Mapping[str, Floats]) -> tuple[float, str, str]:
    worst = {k: float(np.max(v)) for k, v in values.items()}
    hi, lo = max(worst, key=worst.__getitem__), min(worst, key=worst.__getitem__)
    return (worst[hi] / worst[lo] if worst[lo] > 0 else math.inf), hi, lo


def verdict_paths(
    maxe: Mapping[str, Floats], mae: Mapping[str, Floats], limit: float = PATH_SPREAD_LIMIT, claim: str | None = None
) -> Verdict:
    """Similar floors: the worst-joint MaxE and worst-joint MAE differ across paths by ≤ ``limit``×."""
    claim = claim or "the converged errors are similar across the paths"
    crit = criterion_paths(limit)
    if len(maxe) < 2:
        return Verdict(claim, None, "needs at least two paths", crit)
    s_max, hi_m, lo_m = _spread(maxe)
    s_mae, hi_a, lo_a = _spread(mae)
    per_joint = np.array(list(mae.values()), float)
    pj = ", ".join(
        f"j{j + 1} {fmt(per_joint[:, j].max() / per_joint[:, j].min(), 2)}×" if per_joint[:, j].min() > 0 else f"j{j + 1} ∞"
        for j in range(per_joint.shape[1])
    )
    txt = (
        f"worst-joint MaxE spread {fmt(s_max, 2)}× (path {hi_m} vs {lo_m}), worst-joint mean-error spread "
        f"{fmt(s_mae, 2)}× (path {hi_a} vs {lo_a}); per-joint mean-error spread {pj}"
    )
    return Verdict(claim, bool(s_max <= limit and s_mae <= limit), txt, crit)


def verdict_cycles(maxe: Mapping[float, Floats], mae: Mapping[float, Floats], claim: str | None = None) -> Verdict:
    """Slower single journeys give smaller MaxE and MAE on every joint (strictly decreasing in cycle time)."""
    claim = claim or "slower cycles give smaller errors on every joint"
    crit = CRITERION_CYCLES
    cycles = sorted(maxe)
    if len(cycles) < 2:
        return Verdict(claim, None, "needs at least two cycle times", crit)
    bad = []
    near = True
    for name, table in (("MaxE", maxe), ("mean error", mae)):
        for j in range(len(table[cycles[0]])):
            seq = [float(table[c][j]) for c in cycles]
            viol = [i for i in range(len(seq) - 1) if not seq[i + 1] < seq[i]]
            near &= all(seq[i + 1] <= seq[i] * (1 + TIE_FRACTION) for i in viol)
            if viol:
                bad.append(f"{name} j{j + 1}: " + ", ".join(f"{c:g} s {fmt(v)}" for c, v in zip(cycles, seq)))
    tie_note = f" (every violation is within {TIE_FRACTION:.0%}: effectively a tie at the learning floor)" if near else ""
    if not bad:
        mae_txt = "; ".join(f"j{j + 1} " + " > ".join(fmt(float(mae[c][j])) for c in cycles) for j in range(len(mae[cycles[0]])))
        return Verdict(claim, True, f"mean error {', '.join(f'{c:g}' for c in cycles)} s: {mae_txt} deg", crit)
    return Verdict(claim, False, "not decreasing with the cycle time: " + "; ".join(bad) + " deg" + tie_note, crit)


def verdict_profiles_similar(
    maxe_a: Floats, mae_a: Floats, maxe_b: Floats, mae_b: Floats, limit: float = PROFILE_RATIO_LIMIT, claim: str | None = None
) -> Verdict:
    """The controller works as well with both motion laws: worst-joint MaxE and MAE within ``limit``×."""
    claim = claim or "the controller works as well with the 5th-order law as with the 4-5-6-7 law"
    crit = criterion_profiles_similar(limit)
    r_max = max(np.max(maxe_a), np.max(maxe_b)) / max(min(np.max(maxe_a), np.max(maxe_b)), 1e-300)
    r_mae = max(np.max(mae_a), np.max(mae_b)) / max(min(np.max(mae_a), np.max(mae_b)), 1e-300)
    txt = (
        f"worst-joint MaxE {fmt(np.max(maxe_a))} vs {fmt(np.max(maxe_b))} deg ({fmt(r_max, 2)}×), "
        f"worst-joint mean error {fmt(np.max(mae_a))} vs {fmt(np.max(mae_b))} deg ({fmt(r_mae, 2)}×)"
    )
    return Verdict(claim, bool(r_max <= limit and r_mae <= limit), txt, crit)


def verdict_profiles_order(mae_4567: Floats, mae_5: Floats, claim: str | None = None) -> Verdict:
    """The 4-5-6-7 law gives the smaller mean error on every joint."""
    claim = claim or "the 4-5-6-7 law gives the smaller mean error on every joint"
    crit = CRITERION_PROFILES_ORDER
    a, b = np.asarray(mae_4567, float), np.asarray(mae_5, float)
    txt = ", ".join(f"j{j + 1} {fmt(a[j])} vs {fmt(b[j])}" for j in range(len(a)))
    worse = [j for j in range(len(a)) if not a[j] < b[j]]
    if not worse:
        return Verdict(claim, True, f"4567 vs 5th order: {txt} deg", crit)
    tie = all(a[j] <= b[j] * (1 + TIE_FRACTION) for j in worse)
    note = f" (every difference within {TIE_FRACTION:.0%}: effectively a tie)" if tie else ""
    return Verdict(claim, False, f"4567 not smaller on {jlist(worse)}: {txt} deg{note}", crit)


def jlist(idx: Sequence[int]) -> str:
    """Zero-based joint indices as 'j1, j3'."""
    return ", ".join(f"j{i + 1}" for i in idx)

"""The beyond-the-paper sections of the sweep report as markdown lines: the 200-trial runs of
every law (:func:`long_section`) and which law to pick (:func:`beyond_section`: final errors,
settle iterations and floors of every law, the pick, and the paper's claims judged for the laws
beyond it)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from host.analysis.markdown import JOINTS, fmt, md_table
from host.studies.paper.claims import (
    SweepRuns,
    claims_for_law,
    disturbed_floor,
    experiment,
    long_settle,
    long_verdict,
    long_verdicts,
)
from host.studies.paper.convergence_verdicts import LONG_BLOCK, LONG_GROWTH_LIMIT, SETTLE_LIMIT
from host.studies.paper.figures import plot_laws, plot_long
from host.studies.paper.plan import BEYOND_LAWS, DISTURBED, LAW_LABEL, LONG_TRIALS, PAPER_LAW, RunData
from host.studies.paper.verdicts import Verdict
from host.studies.settling import SETTLE_FACTOR, settle_iteration, settled_windows

logger = logging.getLogger(__name__)

__all__ = ["long_section", "beyond_section", "MATRIX_CLAIMS"]

#: the claims of the beyond-the-paper matrix: key of claims_for_law → column header
MATRIX_CLAIMS: dict[str, str] = {
    "table2": "beats D-ILC",
    "fig8_settle": f"settles ≤ {SETTLE_LIMIT}",
    "table3": "disturbance bounded",
    "table4": "paths similar",
    "table5": "slower = smaller",
    "table6_similar": "4567 ≈ 5th",
    "table6_order": "4567 < 5th",
    "long_none": f"stable {LONG_TRIALS}",
    "long_dist": f"stable {LONG_TRIALS}, disturbed",
}


def _long_row(runs: SweepRuns, law: str, dist: str, run: RunData) -> list[str]:
    h = run.metric("rmse_deg")
    m = h.mean(axis=1)
    settle = long_settle(runs, law)
    chk = run.summary["convergence_check"]
    said = chk.get("long_bounded")
    check_word = "—" if said is None else ("bounded" if said else f"NOT bounded ({chk.get('predicted_long_growth', 0.0):.2g}×)")
    cells = ["—"] * 4
    if settle is not None and h.shape[0] >= LONG_BLOCK:
        w = settled_windows(h, LONG_BLOCK, settle)
        best = "—" if w.best_start is None else f"{fmt(w.best_mean_deg)} (k = {w.best_start}..{w.best_start + LONG_BLOCK - 1})"
        ratio = w.last_mean_deg / w.best_mean_deg if w.best_start is not None and w.best_mean_deg > 0 else float("nan")
        cells = [str(w.settle), best, fmt(w.last_mean_deg), fmt(ratio, 3)]
    return (
        [LAW_LABEL.get(law, law), dist, fmt(m[min(9, len(m) - 1)])]
        + cells
        + [long_verdict(runs, law, dist).word, check_word, fmt(chk.get("norm2"), 3)]
    )


def long_section(runs: SweepRuns, out: Path, claims: Mapping[str, Verdict]) -> list[str]:
    """Every law over LONG_TRIALS trials, with and without disturbance; figure ``long_runs.png``."""
    lines = [f"## Beyond the paper's horizon — {LONG_TRIALS} trials", ""]
    found = {
        (law, d): run
        for law in LAW_LABEL
        for d in ("none", DISTURBED)
        if (run := runs.usable(experiment(law, disturbance=d, trials=LONG_TRIALS))) is not None
    }
    if not found:
        return lines + ["not run in this sweep folder (`--only beyond`)", ""]
    plot_long(out / "long_runs.png", found)
    rows = [_long_row(runs, law, dist, run) for (law, dist), run in found.items()]
    lines += [
        f"The paper stops after about 10 iterations. Run longer, a law can still diverge. A run is bounded when the "
        f"mean RMSE over joints of its last {LONG_BLOCK} trials is at most {LONG_GROWTH_LIMIT:g}× the best "
        f"{LONG_BLOCK}-trial mean after settling (deg): the windows start at the settle iteration or later, which is "
        f"the first trial from which every joint stays within {SETTLE_FACTOR:g}× of its final RMSE over the paper's "
        f"horizon (the first {runs.iterations} trials; a disturbed run takes the one without disturbance). Before "
        f"each run the convergence check predicts the same from the linearised model over {LONG_TRIALS} trials (with "
        f"the best {LONG_BLOCK} anywhere in the run; on the nominal plant and on one with twice the inertia; *check* "
        "column) and gives the 2-norm of the trial-to-trial map: a norm above 1 means the error is not guaranteed to "
        "fall at every trial.",
        "",
    ]
    header = ["law", "disturbance", "RMSE at k=9", "settle k", f"best {LONG_BLOCK} after settling", f"last {LONG_BLOCK}"]
    lines += md_table(header + ["last/best", "bounded", "check", "2-norm"], rows)
    lines += ["", "![long runs](long_runs.png)", "", claims["long_none"].line(), claims["long_dist"].line(), ""]
    return lines


def _law_rows(runs: SweepRuns, laws: list[str]) -> tuple[list[list[str]], dict[str, float]]:
    """One row per law (final RMSE, settle k, floor under disturbance, ratios to the paper's law,
    the convergence check) and each law's mean floor under disturbance."""
    base_pd = runs.usable(experiment(PAPER_LAW))
    pd_floor = disturbed_floor(runs, PAPER_LAW)
    rows, score = [], {}
    for law in laws:
        run = runs.need(experiment(law))
        r = run.metric("rmse_deg")
        dfl = disturbed_floor(runs, law)
        ratio_n = (base_pd.metric("rmse_deg")[-1] / r[-1]) if base_pd is not None else None
        ratio_d = (pd_floor / dfl) if pd_floor is not None and dfl is not None else None
        if dfl is not None:
            score[law] = float(np.mean(dfl))
        chk = run.summary["convergence_check"]
        rows.append(
            [LAW_LABEL.get(law, law)]
            + [fmt(x) for x in r[-1]]
            + [str(settle_iteration(r))]
            + ([fmt(x) for x in dfl] if dfl is not None else ["not run"] + [""] * 3)
            + ([f"{fmt(ratio_n[0], 2)} / {fmt(ratio_n[2], 2)}"] if ratio_n is not None else ["—"])
            + ([f"{fmt(ratio_d[0], 2)} / {fmt(ratio_d[2], 2)}"] if ratio_d is not None else ["—"])
            + [
                "not checked"
                if chk.get("checked") is False
                else ("ok" if chk["ok"] else "VIOLATED") + f" ρ={fmt(chk['rho_max'], 3)}"
            ]
        )
    return rows, score


def _pick(runs: SweepRuns, laws: list[str], score: dict[str, float], unstable: list[str]) -> str:
    """The recommendation: the bounded law with the lowest floor under disturbance, set against
    the paper's law and the best law without disturbance."""
    best = min(score, key=score.__getitem__)
    br = runs.need(experiment(best)).metric("rmse_deg")
    und = {law: float(np.mean(runs.need(experiment(law)).metric("rmse_deg")[-1])) for law in laws if law not in unstable}
    best_und = min(und, key=und.__getitem__)
    base_pd = runs.usable(experiment(PAPER_LAW))
    pd_floor = disturbed_floor(runs, PAPER_LAW)
    best_floor = disturbed_floor(runs, best)
    txt = (
        f"**Pick {LAW_LABEL.get(best, best)}**: the lowest error floor under disturbance among the laws "
        f"that stay bounded (mean over joints {fmt(score[best])} deg"
    )
    if base_pd is not None and pd_floor is not None and best_floor is not None and best != PAPER_LAW:
        pr = base_pd.metric("rmse_deg")
        rn = pr[-1] / br[-1]
        rd = pd_floor / best_floor
        txt += (
            f" vs {fmt(float(np.mean(pd_floor)))} for the paper's PD-ILC). Against the paper's law "
            f"its final RMSE without disturbance is {fmt(rn[0], 2)}× (j1) / {fmt(rn[2], 2)}× (j3) smaller, its "
            f"floor with disturbance {fmt(rd[0], 2)}× / {fmt(rd[2], 2)}× smaller, and it settles at k = "
            f"{settle_iteration(br)} vs {settle_iteration(pr)}."
        )
    else:
        txt += ").  The paper's law is already the best of those run." if best == PAPER_LAW else ")."
    if best_und != best:
        txt += (
            f" Without disturbance {LAW_LABEL.get(best_und, best_und)} reaches the lowest final error "
            f"({fmt(und[best_und])} deg mean over joints vs {fmt(und[best])}), but under the non-repeatable "
            f"disturbance its floor is {fmt(score.get(best_und, float('nan')))} deg: it learns the "
            "non-repeatable part as if it would repeat."
        )
    ties = [law for law in score if law != best and score[law] <= 1.05 * score[best]]
    if ties:
        txt += (
            " Within 5 % of it under disturbance: "
            + ", ".join(f"{LAW_LABEL.get(law, law)} ({fmt(score[law])} deg)" for law in ties)
            + " — effectively a tie."
        )
    return txt


def _matrix(runs: SweepRuns) -> tuple[list[str], dict[str, Verdict]]:
    """The paper's claims judged for the laws beyond it: a matrix and the failing verdicts' lines."""
    verdicts: dict[str, Verdict] = {}
    rows = []
    for law in BEYOND_LAWS:
        if runs.usable(experiment(law)) is None:
            continue
        cl = claims_for_law(runs, law)
        verdicts.update({f"{law}:{k}": vv for k, vv in cl.items()})
        rows.append([LAW_LABEL[law]] + [cl[k].word for k in MATRIX_CLAIMS])
    if not rows:
        return [], verdicts
    lines = ["The paper's claims evaluated for the laws beyond it (same criteria):", ""]
    lines += md_table(["law"] + list(MATRIX_CLAIMS.values()), rows) + [""]
    lines += [vv.line() for vv in verdicts.values() if vv.holds is False]
    return lines + [""], verdicts


def beyond_section(runs: SweepRuns, out: Path) -> tuple[list[str], dict[str, Verdict]]:
    """Which law to pick: every law on path 1 with and without disturbance (figure
    ``convergence_laws.png``), the pick, and the paper's claims for the laws beyond it."""
    laws = [law for law in LAW_LABEL if runs.usable(experiment(law)) is not None]
    lines = ["## Beyond the paper — which law to pick", ""]
    if not laws:
        return lines + ["not run", ""], {}
    plot_runs = {(law, d): runs.usable(experiment(law, disturbance=d)) for law in laws for d in ("none", DISTURBED)}
    plot_laws(out / "convergence_laws.png", {k: v for k, v in plot_runs.items() if v is not None})
    rows, score = _law_rows(runs, laws)
    lines += [
        "Path 1, 0.25 s, 4-5-6-7 law. *final* = last trial without disturbance; *settle k* = the first trial from "
        f"which every joint stays within {SETTLE_FACTOR:g}× of its final RMSE, without disturbance; *floor* = mean "
        f"RMSE with disturbance '{DISTURBED}' over the trials from that settle iteration on; *ratio* = the "
        "paper's law (PD-ILC) over this law, joints 1 / 3 (> 1: this law is better); the convergence check is the "
        "lifted-model spectral radius run before each experiment.",
        "",
    ]
    lines += md_table(
        ["law"]
        + [f"final RMSE j{j}" for j in JOINTS]
        + ["settle k"]
        + [f"floor j{j}" for j in JOINTS]
        + ["ratio final j1/j3", "ratio floor j1/j3", "check"],
        rows,
    )
    lines += ["", "![all laws](convergence_laws.png)", ""]
    unstable = sorted(law for law in laws if any(v.holds is False for v in long_verdicts(runs, law).values()))
    if unstable:
        lines += [
            f"Not eligible: {', '.join(LAW_LABEL.get(name, name) for name in unstable)} — not bounded over "
            f"{LONG_TRIALS} trials (see the section above).",
            "",
        ]
    score = {law: sc for law, sc in score.items() if law not in unstable}
    if score:
        lines += [_pick(runs, laws, score, unstable), ""]
    matrix, verdicts = _matrix(runs)
    return lines + matrix, verdicts

"""The figures of the paper's report: Figs. 8/10 (RMSE vs iteration, PD-ILC and D-ILC), every law's
convergence, and the long runs (on the Agg canvas of :mod:`host.analysis.figures`, written
atomically).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from host.analysis.figures import figure, save_png
from host.studies.paper.plan import LAW_LABEL, LONG_TRIALS, RunData

logger = logging.getLogger(__name__)

__all__ = ["plot_fig8", "plot_laws", "plot_long"]


def plot_fig8(path: Path, runs: Mapping[str, RunData], title: str) -> Path:
    """RMSE vs iteration: (A) joints 1 & 3, (B) joints 2 & 4, one line per law and joint."""
    fig, ax = figure(1, 2, 11, 4.2)
    styles = {1: "-", 2: "-", 3: "--", 4: "--"}
    colors = {"pd-ilc": "tab:red", "d-ilc": "tab:blue"}
    for a, joints, tag in ((ax[0, 0], (1, 3), "(A) joints 1 and 3"), (ax[0, 1], (2, 4), "(B) joints 2 and 4")):
        for law, run in runs.items():
            r = run.metric("rmse_deg")
            k = np.arange(r.shape[0])
            for j in joints:
                a.plot(
                    k,
                    r[:, j - 1],
                    styles[j],
                    marker="o",
                    ms=3,
                    color=colors.get(law),
                    label=f"{LAW_LABEL.get(law, law)} joint {j}",
                )
        a.set_yscale("log")
        a.set_xlabel("iteration k (k = 0: before learning)")
        a.set_ylabel("RMSE [deg]")
        a.set_title(tag)
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8)
    fig.suptitle(title)
    return save_png(fig, path)


def plot_laws(path: Path, runs: Mapping[tuple[str, str], RunData]) -> Path:
    """RMSE vs iteration per joint for every law; solid: no disturbance, dashed: with disturbance."""
    fig, ax = figure(2, 2, 11, 8)
    laws = sorted({law for law, _ in runs}, key=lambda s: list(LAW_LABEL).index(s) if s in LAW_LABEL else 99)
    cmap = {law: f"C{i}" for i, law in enumerate(laws)}
    for j in range(4):
        a = ax[j // 2, j % 2]
        for (law, dist), run in sorted(runs.items(), key=lambda kv: (laws.index(kv[0][0]), kv[0][1] != "none")):
            r = run.metric("rmse_deg")
            a.plot(
                np.arange(r.shape[0]),
                r[:, j],
                "-" if dist == "none" else "--",
                marker=".",
                color=cmap[law],
                label=f"{LAW_LABEL.get(law, law)}{'' if dist == 'none' else ', disturbed'}",
            )
        a.set_yscale("log")
        a.set_title(f"joint {j + 1}")
        a.set_xlabel("iteration k")
        a.set_ylabel("RMSE [deg]")
        a.grid(True, which="both", alpha=0.3)
        if j == 0:
            a.legend(fontsize=7, ncol=2)
    fig.suptitle("Convergence of every law (path 1, 0.25 s, 4-5-6-7 law)")
    return save_png(fig, path)


def plot_long(path: Path, runs: Mapping[tuple[str, str], RunData]) -> Path:
    """Mean RMSE over joints vs iteration of the long runs; solid: no disturbance, dashed: disturbed."""
    fig, ax = figure(1, 1, 9, 5)
    a = ax[0, 0]
    laws = [law for law in LAW_LABEL if any(k[0] == law for k in runs)]
    for (law, dist), run in sorted(runs.items(), key=lambda kv: (laws.index(kv[0][0]), kv[0][1] != "none")):
        r = run.metric("rmse_deg").mean(axis=1)
        a.plot(
            np.arange(r.shape[0]),
            r,
            "-" if dist == "none" else "--",
            marker=".",
            color=f"C{laws.index(law)}",
            label=f"{LAW_LABEL.get(law, law)}{'' if dist == 'none' else ', disturbed'}",
        )
    a.set_yscale("log")
    a.set_xlabel("iteration k")
    a.set_ylabel("RMSE, mean over joints [deg]")
    a.grid(True, which="both", alpha=0.3)
    a.legend(fontsize=7, ncol=2)
    a.set_title(f"Long runs: {LONG_TRIALS} trials, path 1, 0.25 s, 4-5-6-7 law")
    return save_png(fig, path)

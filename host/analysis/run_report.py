"""The report of one run folder (``ilcrig sim`` / ``ilcrig run``): ``report.md`` with the
per-trial RMSE / MaxE / MAE table, the convergence check, any fault (kind, node, trial, tick, who
detected it and how fast) or interrupt, the drives' safe state after it, and ``convergence.png``
over the completed trials.  Both files are replaced atomically (a failing write leaves no
temporary file behind)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from bus.atomic import atomic_write
from host.analysis.figures import figure, save_png
from host.analysis.markdown import JOINTS, fmt, md_table
from host.experiment.faults import FaultRecord, position_words

__all__ = ["write_run_report"]


def _command(summary: Mapping[str, Any]) -> str:
    """The command that made the run (the summary's mode: ``sim`` in one process, else the rig)."""
    return "sim" if summary.get("mode") == "sim" else "run"


def write_run_report(run_dir: str | Path, summary: Mapping[str, Any]) -> Path:
    """``report.md`` + ``convergence.png`` for one run folder from its summary (``ilcrig sim``/``run``)."""
    d = Path(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    cfg = summary.get("config", {})
    its = summary.get("iterations", [])
    chk = summary.get("convergence_check", {})
    lines = [
        f"# ilcrig {_command(summary)} — {cfg.get('law', '?')}, path {cfg.get('path', '?')}, {cfg.get('cycle_s', '?')} s, "
        f"{cfg.get('profile', '?')}, disturbance {cfg.get('disturbance', '?')}",
        "",
        f"Mode {summary.get('mode', '?')}; {len(its)} of {cfg.get('iterations', '?')} trials"
        f"{' (completed)' if summary.get('completed') else ''}; N = {cfg.get('n_ticks', '?')} ticks per trial; "
        f"trace_sha256 `{str(summary.get('trace_sha256', ''))[:16]}…`.",
        "",
    ]
    if chk:
        long = chk.get("long_bounded")
        long_txt = (
            ""
            if long is None
            else (
                f"; over {chk.get('long_horizon')} trials {'bounded' if long else 'NOT bounded'}"
                + (
                    ""
                    if long
                    else f" (predicted growth {chk.get('predicted_long_growth', 0.0):.2g}×, {chk.get('long_worst_case', '?')})"
                )
            )
        )
        if chk.get("checked") is False:
            why = str(chk.get("prediction") or "the law gives no linear iteration map").removeprefix("not checked: ")
            lines += [f"Convergence check: not checked ({why}).", ""]
        else:
            lines += [
                f"Convergence check: spectral radius {fmt(chk.get('rho_max'), 4)} "
                f"({'ok' if chk.get('ok') else 'VIOLATED'}), 2-norm {fmt(chk.get('norm2'), 4)}{long_txt}.",
                "",
            ]
    for f in summary.get("faults", []):
        lat = f.get("latency_ms")
        lines += [
            f"**Fault** ({f.get('kind', '?')}) at {FaultRecord.from_dict(dict(f)).where()}: {f.get('message')} — detected by "
            f"{f.get('detected_by', '?')}{f' after {lat:.0f} ms' if isinstance(lat, int | float) else ''}.",
            "",
        ]
    if summary.get("interrupted"):
        i = summary["interrupted"]
        where = position_words(i.get("position"), i.get("trial"), i.get("tick"))
        lines += [f"**Interrupted** by {i.get('signal')}, {where}.", ""]
    safe = summary.get("safe_state") or []
    if safe and (summary.get("faults") or summary.get("interrupted")):
        lines += ["Safe state after the run:", ""]
        lines += md_table(
            ["node", "torque", "evidence"], [[str(x.get("node")), str(x.get("torque")), str(x.get("evidence"))] for x in safe]
        )
        lines += [""]
    rows = [
        [str(it["k"])] + [fmt(v) for v in it["rmse_deg"]] + [fmt(v) for v in it["max_abs_deg"]] + [fmt(v) for v in it["mae_deg"]]
        for it in its
    ]
    lines += md_table(
        ["k"] + [f"RMSE j{j}" for j in JOINTS] + [f"MaxE j{j}" for j in JOINTS] + [f"MAE j{j}" for j in JOINTS], rows
    )
    lines += ["", "Errors in deg (e = q_d − q); k = 0 is the first trial.", ""]
    if its:
        r = np.array([it["rmse_deg"] for it in its], dtype=float)
        fig, ax = figure(1, 1, 7, 4)
        a = ax[0, 0]
        for j in range(r.shape[1]):
            a.plot(np.arange(r.shape[0]), r[:, j], marker="o", ms=3, label=f"joint {j + 1}")
        if np.all(r > 0):
            a.set_yscale("log")
        a.set_xlabel("trial k")
        a.set_ylabel("RMSE [deg]")
        a.grid(True, which="both", alpha=0.3)
        a.legend()
        a.set_title(f"{cfg.get('law', '?')}: RMSE per trial")
        try:
            save_png(fig, d / "convergence.png")
            lines += ["![convergence](convergence.png)", ""]
        except OSError as err:
            lines += [f"(convergence.png could not be written: {err.strerror or err})", ""]
    return atomic_write(d / "report.md", "\n".join(lines))

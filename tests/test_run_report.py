"""report.md of one run folder (host/analysis/run_report.py) says what happened: the command that
made the run in its title, and "not checked" where no convergence check ran."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from host.analysis.run_report import write_run_report


def _summary(mode: str, check: dict[str, Any]) -> dict[str, Any]:
    return {
        "mode": mode,
        "config": {
            "law": "adjoint-ilc",
            "path": "1",
            "cycle_s": 0.25,
            "profile": "ruckig",
            "disturbance": "none",
            "iterations": 2,
        },
        "iterations": [],
        "convergence_check": check,
        "completed": True,
        "trace_sha256": "0" * 64,
    }


NOT_CHECKED = {
    "checked": False,
    "ok": None,
    "rho_max": None,
    "norm2": None,
    "prediction": "not checked: law adjoint-ilc gives no linear iteration map",
}
CHECKED = {"checked": True, "ok": True, "rho_max": 0.5, "norm2": 0.9}


def test_a_law_without_an_iteration_map_is_reported_not_checked(tmp_path: Path) -> None:
    text = write_run_report(tmp_path, _summary("sim", NOT_CHECKED)).read_text()
    assert "Convergence check: not checked (law adjoint-ilc gives no linear iteration map)." in text
    assert "VIOLATED" not in text


def test_a_checked_law_is_reported_with_its_spectral_radius(tmp_path: Path) -> None:
    text = write_run_report(tmp_path, _summary("sim", CHECKED)).read_text()
    assert "Convergence check: spectral radius 0.5 (ok)" in text


def test_the_title_names_the_command_that_made_the_run(tmp_path: Path) -> None:
    assert write_run_report(tmp_path / "s", _summary("sim", CHECKED)).read_text().startswith("# ilcrig sim — adjoint-ilc")
    assert write_run_report(tmp_path / "r", _summary("rig", CHECKED)).read_text().startswith("# ilcrig run — adjoint-ilc")

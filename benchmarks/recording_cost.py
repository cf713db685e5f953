"""Benchmark: what writing recording.rrd costs, next to the same experiment without a recorder.

The test suite checks what the recorder does (no call into Rerun per sample or per trial); this
script measures what it costs.  The experiment is
the default one as ``ilcrig sim`` runs it (``--iterations`` trials, cycle 0.25 s, N = 501); per
repeat, one ``run_experiment`` on the in-process bench without a recorder (the floor, measured in
this run) and one with a fresh :class:`host.analysis.recording.RunRecorder` (its creation, the
``log_trial`` calls and ``close`` included).  Best of ``--repeat``; the cost is the difference
of the wall times, printed against run_experiment alone and against prepare + run_experiment
(what ``ilcrig sim`` spends), with process CPU times.  Target: < 10 % of prepare + run.

    python benchmarks/recording_cost.py [--iterations 10] [--repeat 3]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))


def timed_experiment(cfg: Any, plan: Any, folder: Path | None) -> tuple[float, float]:
    """(wall s, process CPU s) of one run_experiment, including the recorder's creation."""
    from host.analysis.recording import RunRecorder
    from host.experiment.trial_loop import run_experiment
    from host.sim.inprocess import InProcessBench

    w0, c0 = time.perf_counter(), time.process_time()
    rec = RunRecorder(folder / "recording.rrd", config_summary=cfg.as_dict()) if folder is not None else None
    run_experiment(plan, InProcessBench(cfg), None, mode="sim", recorder=rec)
    if rec is not None and rec.error is not None:
        raise RuntimeError(f"recording failed: {rec.error}")
    return time.perf_counter() - w0, time.process_time() - c0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    import rerun  # noqa: F401  (import cost is per process, not per experiment)

    from host.experiment.config import build_config
    from host.experiment.plan import prepare

    cfg = build_config(None, {"iterations": args.iterations})
    t0 = time.perf_counter()
    plan = prepare(cfg)
    prepare_s = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        timed_experiment(cfg, plan, Path(tmp) / "warm")  # warm caches (numba, rerun)
        without, with_rec = [], []
        for i in range(args.repeat):
            without.append(timed_experiment(cfg, plan, None))
            with_rec.append(timed_experiment(cfg, plan, Path(tmp) / f"r{i}"))
        size = (Path(tmp) / "r0" / "recording.rrd").stat().st_size
    wall0, wall1 = min(w for w, _ in without), min(w for w, _ in with_rec)
    cpu0, cpu1 = min(c for _, c in without), min(c for _, c in with_rec)
    cost = wall1 - wall0
    print(
        f"ilcrig recording benchmark: default experiment, {args.iterations} trials of N = {plan.ref.t.shape[0]}, "
        f"best of {args.repeat}"
    )
    print(f"{'':<30}{'wall s':>10}{'cpu s':>10}")
    print(f"{'prepare':<30}{prepare_s:>10.3f}{'':>10}")
    print(f"{'run_experiment (floor)':<30}{wall0:>10.3f}{cpu0:>10.3f}")
    print(f"{'run_experiment + recorder':<30}{wall1:>10.3f}{cpu1:>10.3f}")
    print(
        f"recording: +{cost * 1e3:.1f} ms wall, {size / 1e6:.2f} MB; "
        f"{cost / wall0:.1%} of run_experiment, {cost / (prepare_s + wall0):.1%} of prepare + run "
        f"(target < 10 %)"
    )


if __name__ == "__main__":
    main()

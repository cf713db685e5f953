"""Benchmark: the sweep engine (Dask distributed) — points per second against the number of workers,
Dask's overhead per point against a plain process pool, and ``ilcrig reproduce`` against the
process-pool engine it replaced.

Scaling (default): ``--points`` points (``pd-ilc-q`` on the paper's condition: path 1, 4-5-6-7
law, ``--trials`` 10 trials of a ``--cycle`` 0.25 s cycle; each gain α a point) on ``--workers``
(a list: the scaling can be measured on any machine) worker processes, once on a Dask
``LocalCluster`` (:func:`host.studies.engine.run_points`) and once on a plain
``ProcessPoolExecutor`` running the same point function and writing the same folders,
alternately, ``--repeat`` times each.  Both are warmed up first (every worker: imports, numba's
cache); the cluster's start is timed on its own.  The overhead per point is (t_dask − t_pool) /
points, in wall time and in CPU time (this process and its workers: user + system; on a machine
shared with other work the CPU time is the steadier figure).

    python benchmarks/sweep_speed.py [--workers 1,2] [--points 16] [--repeat 3] [--trials 10] [--cycle 0.25]

Reproduce (``--reproduce REV``): ``ilcrig reproduce --jobs 2`` of this tree and of the tree at git
revision ``REV`` (its engine; extracted with ``git archive``), alternately, ``--repeat`` times each,
after a warm-up of each (numba's cache of its tree); then the two ``report.md`` compared line by
line with the runs table's wall-time column left out.

    python benchmarks/sweep_speed.py --reproduce 66d1e20 [--repeat 2] [--iterations 10] [--only …]

The machine's load average is printed beside every timing (a shared machine's timings move with it).
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def load() -> str:
    """The 1-minute load average and the number of cores."""
    return f"load {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"


def cpu_s() -> float:
    """CPU seconds (user + system) of this process and its live descendants (the workers): what a
    run costs, less sensitive than wall time to the other work of a shared machine."""
    import psutil

    me = psutil.Process()
    total = 0.0
    for p in [me, *me.children(recursive=True)]:
        try:
            t = p.cpu_times()
        except psutil.NoSuchProcess:
            continue
        total += t.user + t.system
    return total


#: the experiment of a point: ``--trials`` and ``--cycle`` set its size
POINT: dict[str, Any] = {"law": "pd-ilc-q", "path": "1", "profile": "poly4567", "iterations": 10, "cycle_s": 0.25}


def _points(n: int, tag: float) -> list[Any]:
    """``n`` distinct points, each gain α another (``tag`` keeps the runs of a benchmark apart)."""
    from host.studies.spec import Point

    return [Point.of(POINT | {"gains": {"alpha": 2.0 + tag + i / (10 * n)}}, index=i) for i in range(n)]


def _init() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def pool_run(pool: ProcessPoolExecutor, out: Path, points: list[Any]) -> float:
    """The points on the process pool, each result written as the engine writes it; wall s."""
    from host.studies.engine import point_doc
    from host.studies.point import commit, run_point

    t0 = time.perf_counter()
    futures = {pool.submit(run_point, p.id, p.options, False): p for p in points}
    for f in as_completed(futures):
        p = futures[f]
        commit(out, p.id, point_doc(p), f.result())
    return time.perf_counter() - t0


def dask_run(engine: Any, out: Path, points: list[Any]) -> float:
    from host.studies.engine import run_points

    t0 = time.perf_counter()
    outcome = run_points(engine, out, points, progress=False)
    assert len(outcome.ran) == len(points) and not outcome.errors
    return time.perf_counter() - t0


def scaling(workers: list[int], n_points: int, repeat: int) -> None:
    from host.studies.engine import Engine
    from host.studies.point import run_point

    print(
        f"sweep engine scaling: {n_points} points ({POINT['law']}, {POINT['iterations']} trials of a {POINT['cycle_s']} s "
        f"cycle, path {POINT['path']}, {POINT['profile']}) per run, {repeat} runs per engine"
    )
    with tempfile.TemporaryDirectory(prefix="sweep-speed-") as tmp:
        base = Path(tmp)
        for w in workers:
            t0 = time.perf_counter()
            engine = Engine(workers=w, dashboard=False)
            engine.start()
            t_start = time.perf_counter() - t0
            pool = ProcessPoolExecutor(max_workers=w, mp_context=multiprocessing.get_context("spawn"), initializer=_init)
            try:
                # warm-up of every worker process (imports, numba's cache): on each Dask worker, and
                # enough points that every pool process gets some
                warm = _points(1, 0.5)[0]
                engine.client.run(run_point, warm.id, warm.options, False)
                pool_run(pool, base / f"warm-p{w}", _points(4 * w, 0.6))
                t_dask, t_pool, c_dask, c_pool = [], [], [], []
                for r in range(repeat):
                    c0 = cpu_s()
                    t_dask.append(dask_run(engine, base / f"d{w}-{r}", _points(n_points, 1.0 + r)))
                    c_dask.append(cpu_s() - c0)
                    print(
                        f"  {w} worker(s), run {r}: dask {n_points / t_dask[-1]:.2f} points/s, "
                        f"{1000 * c_dask[-1] / n_points:.0f} ms CPU per point ({load()})"
                    )
                    c0 = cpu_s()
                    t_pool.append(pool_run(pool, base / f"p{w}-{r}", _points(n_points, 1.0 + r + 0.5)))
                    c_pool.append(cpu_s() - c0)
                    print(
                        f"  {w} worker(s), run {r}: pool {n_points / t_pool[-1]:.2f} points/s, "
                        f"{1000 * c_pool[-1] / n_points:.0f} ms CPU per point ({load()})"
                    )
            finally:
                engine.close()
                pool.shutdown(wait=True)
            d, p = statistics.median(t_dask), statistics.median(t_pool)
            cd, cp = statistics.median(c_dask), statistics.median(c_pool)
            print(
                f"{w} worker(s): dask {n_points / d:.2f} points/s, process pool {n_points / p:.2f} points/s (medians); "
                f"Dask's overhead {1000 * (d - p) / n_points:+.1f} ms per point ({100 * (d - p) / p:+.1f} %) in wall time, "
                f"{1000 * (cd - cp) / n_points:+.1f} ms ({100 * (cd - cp) / cp:+.1f} %) in CPU time "
                f"(all processes: {1000 * cd / n_points:.0f} against {1000 * cp / n_points:.0f} ms per point); "
                f"cluster start {t_start:.2f} s"
            )


def _tree(rev: str, dest: Path) -> Path:
    """The project at git revision ``rev``, extracted into ``dest`` (git archive: nothing of the
    repository changes)."""
    dest.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest


def _children_cpu_s() -> float:
    """CPU seconds (user + system) of every descendant process waited for so far."""
    import resource

    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _reproduce(tree: Path, out: Path, args: list[str]) -> tuple[float, float, float]:
    """``ilcrig reproduce`` of ``tree`` (its packages first on the path): (wall s of the command,
    wall s of the experiments as the command reports it, CPU s of the command and its workers)."""
    c0 = _children_cpu_s()
    t0 = time.perf_counter()
    p = subprocess.run(
        [sys.executable, "-m", "host.cli", "reproduce", "--out", str(out), *args],
        cwd=tree,
        capture_output=True,
        text=True,
        env=os.environ | {"PYTHONPATH": str(tree)},
    )
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"reproduce in {tree} failed ({p.returncode}): {p.stderr[-2000:]}")
    m = re.search(r"already finished, ([0-9.]+) s on", p.stdout)
    return wall, float(m.group(1)) if m else float("nan"), _children_cpu_s() - c0


def _report_lines(path: Path) -> list[str]:
    """report.md without the wall-time column of its runs table."""
    out, in_runs = [], False
    for line in path.read_text().splitlines():
        if line.startswith("## "):
            in_runs = line.strip() == "## Runs"
        if in_runs and line.startswith("|"):
            cells = line.split("|")
            line = "|".join(cells[:3] + cells[4:])
        out.append(line)
    return out


def reproduce(rev: str, repeat: int, iterations: int, only: str | None, jobs: int) -> None:
    common = ["--jobs", str(jobs), "--iterations", str(iterations)] + (["--only", only] if only else [])
    with tempfile.TemporaryDirectory(prefix="sweep-speed-reproduce-") as tmp:
        base = Path(tmp)
        old = _tree(rev, base / "old-tree")
        trees = {"new (Dask)": ROOT, f"old ({rev}, process pool)": old}
        for i, tree in enumerate(trees.values()):  # numba's cache of each tree, imports
            _reproduce(tree, base / f"warm-{i}", ["--jobs", str(jobs), "--iterations", "1", "--only", "table2"])
        walls: dict[str, list[float]] = {name: [] for name in trees}
        sweeps: dict[str, list[float]] = {name: [] for name in trees}
        cpus: dict[str, list[float]] = {name: [] for name in trees}
        outs: dict[str, Path] = {}
        print(f"ilcrig reproduce {' '.join(common)}: new engine and the one of {rev}, alternately, {repeat} runs each")
        for r in range(repeat):
            for i, (name, tree) in enumerate(trees.items()):
                outs[name] = base / f"run-{r}-{i}"
                before = load()
                wall, sweep, cpu = _reproduce(tree, outs[name], common)
                walls[name].append(wall)
                sweeps[name].append(sweep)
                cpus[name].append(cpu)
                print(
                    f"  run {r}, {name}: {wall:.1f} s, of which {sweep:.1f} s running the experiments; "
                    f"{cpu:.1f} CPU s (before: {before}; after: {load()})"
                )
        for name, w in walls.items():
            print(
                f"{name}: median {statistics.median(w):.1f} s over {len(w)} runs ({', '.join(f'{x:.1f}' for x in w)}); "
                f"running the experiments: median {statistics.median(sweeps[name]):.1f} s; "
                f"CPU: median {statistics.median(cpus[name]):.1f} s ({', '.join(f'{x:.1f}' for x in cpus[name])})"
            )
        new, old_name = list(trees)
        a, b = _report_lines(outs[new] / "report.md"), _report_lines(outs[old_name] / "report.md")
        diff = [(i, x, y) for i, (x, y) in enumerate(zip(a, b)) if x != y]
        same = len(a) == len(b) and not diff
        print(f"report.md of both (the runs table's wall-time column left out): {'the same' if same else 'DIFFERENT'}")
        for i, x, y in diff[:10]:
            print(f"  line {i + 1}:\n    new {x}\n    old {y}")
        if len(a) != len(b):
            print(f"  {len(a)} lines (new) against {len(b)} (old)")
        shutil.rmtree(old, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", default="1,2", help="worker counts to measure, comma-separated (default 1,2)")
    ap.add_argument("--points", type=int, default=16, help="points per run (default 16)")
    ap.add_argument("--trials", type=int, default=10, help="trials per point (default 10, the paper's)")
    ap.add_argument("--cycle", type=float, default=0.25, help="cycle time of a point, s (default 0.25, the paper's)")
    ap.add_argument("--repeat", type=int, default=None, help="runs per engine (default 3; --reproduce: 2)")
    ap.add_argument("--reproduce", metavar="REV", help="compare ilcrig reproduce with the engine of git revision REV")
    ap.add_argument("--iterations", type=int, default=10, help="--reproduce: trials per experiment (default 10)")
    ap.add_argument("--only", default=None, help="--reproduce: a subset of the experiments (default all)")
    ap.add_argument("--jobs", type=int, default=2, help="--reproduce: worker processes (default 2)")
    args = ap.parse_args()
    if args.reproduce:
        reproduce(args.reproduce, args.repeat or 2, args.iterations, args.only, args.jobs)
    else:
        POINT.update(iterations=args.trials, cycle_s=args.cycle)
        scaling([int(w) for w in args.workers.split(",")], args.points, args.repeat or 3)


if __name__ == "__main__":
    main()

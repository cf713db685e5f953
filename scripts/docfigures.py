#!/usr/bin/env python3
"""The figures that README.md and docs/*.md state, generated from the commands that produce them.

Two kinds of statement are kept true here:

* **digest lines**: a line of a fenced code block of the form
  ``ilcrig sim [options]   # … trace_sha256 0123abcd…`` states the digest that command prints;
  :func:`check_digest_lines` runs each such command and compares the stated prefix (a line that
  starts with ``ilcrig run`` is run as ``ilcrig sim`` with the same experiment options: the two
  give the same digest by construction, which the rig tests check on every transport);
* **figure blocks**: the text between ``<!-- figures: NAME -->`` and ``<!-- /figures -->`` is the
  output of the generator ``NAME`` of :data:`GENERATORS`, which runs the command it names and
  renders its result as markdown.

``python scripts/docfigures.py`` checks every file and prints what differs (exit 1 if anything
does); ``python scripts/docfigures.py --write`` regenerates the blocks in place (digest lines are
never rewritten: a changed digest is a decision to state in a closing note, then edit by hand).
``tests/test_docs_truth.py`` runs the check.

``ilcrig sim`` commands run through :func:`host.cli.main` in one worker process, ``ilcrig run`` as its
own process tree, each with its ``--out`` in a temporary folder; results are cached per command
within one run of this script.
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
#: the files whose statements are checked
DOC_FILES = ("README.md", "docs/*.md")

BLOCK_RE = re.compile(r"(<!-- figures: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /figures -->)", re.S)
DIGEST_RE = re.compile(r"^(?P<cmd>ilcrig (?:sim|run)\b[^#\n]*?)\s*#[^\n]*?trace_sha256 (?P<hex>[0-9a-f]{8,64})…?", re.M)
#: options of ``ilcrig run`` that do not change the experiment (left out when run as ``sim``)
RUN_ONLY_OPTIONS = {"--realtime": 0, "--bus-time": 0, "--bus": 1, "--hub": 1, "--rt-priority": 1, "--no-idle-poll": 0}

DEG_PER_COUNT = 360.0 / (10 * 2**20)  # = bus.units.DEG_PER_COUNT (this script imports nothing of the project)


def doc_files() -> list[Path]:
    out: list[Path] = []
    for pattern in DOC_FILES:
        out.extend(sorted(ROOT.glob(pattern)))
    return out


# ----------------------------------------------------------------------------- running commands


#: the worker that runs ``ilcrig sim`` commands one after another in one interpreter (the imports
#: and numba's compilation are paid once): one JSON argv per line in, one exit code per line out
_WORKER = r"""
import contextlib, io, json, sys
from host.cli import main
for line in sys.stdin:
    argv = json.loads(line)
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            rc = main(argv)
        except SystemExit as exc:
            rc = exc.code if isinstance(exc.code, int) else 1
    print(json.dumps([rc, err.getvalue()[-500:]]), flush=True)
"""


class Runner:
    """Runs ``ilcrig`` commands once each and returns their summaries.

    ``ilcrig sim`` commands go through :func:`host.cli.main` in one long-lived worker process (the
    same code path as the console script); other commands (``ilcrig run``) run as their own
    process tree, as a user would start them.
    """

    def __init__(self) -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix="ilcrig-docfigures-")
        self._cache: dict[tuple[str, ...], dict[str, Any]] = {}
        self._folders: dict[tuple[str, ...], Path] = {}
        self._n = 0
        self._worker: subprocess.Popen[str] | None = None

    def close(self) -> None:
        if self._worker is not None:
            assert self._worker.stdin is not None
            self._worker.stdin.close()
            self._worker.wait(timeout=60)
        self._tmp.cleanup()

    def _run_in_worker(self, argv: list[str]) -> tuple[int, str]:
        if self._worker is None:
            self._worker = subprocess.Popen(
                [sys.executable, "-P", "-c", _WORKER], cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
            )
        assert self._worker.stdin is not None and self._worker.stdout is not None
        self._worker.stdin.write(json.dumps(argv) + "\n")
        self._worker.stdin.flush()
        line = self._worker.stdout.readline()
        if not line:
            raise RuntimeError(f"the docfigures worker ended while running {argv}")
        rc, err = json.loads(line)
        return int(rc), str(err)

    def summary(self, command: str, *args: str) -> dict[str, Any]:
        """``summary.json`` of ``ilcrig COMMAND ARGS --out TMP`` (which must exit 0)."""
        key = (command, *args)
        if key not in self._cache:
            self._n += 1
            out = Path(self._tmp.name) / f"run{self._n}"
            argv = [command, *args, "--out", str(out)]
            if command == "sim":
                rc, err = self._run_in_worker(argv)
            else:
                proc = subprocess.run(
                    [sys.executable, "-P", "-m", "host.cli", *argv], cwd=ROOT, capture_output=True, text=True, timeout=900
                )
                rc, err = proc.returncode, proc.stderr[-500:]
            if rc != 0:
                raise RuntimeError(f"ilcrig {' '.join(argv)} exited {rc}: {err.strip()}")
            self._cache[key] = json.loads((out / "summary.json").read_text())
            self._folders[key] = out
        return self._cache[key]

    def folder(self, command: str, *args: str) -> Path:
        """The run folder of ``ilcrig COMMAND ARGS`` (run first if it has not been)."""
        self.summary(command, *args)
        return self._folders[(command, *args)]

    def config_file(self, name: str, text: str) -> str:
        """A TOML config file with ``text`` in the temporary folder; its path."""
        path = Path(self._tmp.name) / name
        path.write_text(text)
        return str(path)


# ----------------------------------------------------------------------------- helpers


def _rmse_deg(summary: dict[str, Any], k: int) -> list[float]:
    return [float(x) for x in summary["iterations"][k]["rmse_deg"]]


def _counts(deg: float) -> float:
    return deg / DEG_PER_COUNT


def _fmt(x: float) -> str:
    return f"{x:.3g}" if abs(x) >= 1e-3 else f"{x:.2e}"


#: the factor within which an approximate figure (``~7e-04``) must agree with what its command gives
APPROX_FACTOR = 2.0
_NUMBER_RE = re.compile(r"~?[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?")


def _approx(x: float) -> str:
    """A figure that is not reproducible across CPUs (an ill-conditioned solve rounds differently
    on another CPU's BLAS kernels): one significant digit, marked ``~``, checked within a factor of
    :data:`APPROX_FACTOR` (:func:`same_figures`)."""
    return f"~{x:.0e}"


def same_figures(stated: str, computed: str) -> bool:
    """Whether a figure block as stated agrees with the block its command gives now: the same text,
    except that a number stated as ``~X`` only has to be within a factor of :data:`APPROX_FACTOR` of
    the computed one (which is then also marked ``~``)."""
    if stated == computed:
        return True
    a, b = _NUMBER_RE.split(stated), _NUMBER_RE.split(computed)
    na, nb = _NUMBER_RE.findall(stated), _NUMBER_RE.findall(computed)
    if a != b or len(na) != len(nb):
        return False
    for x, y in zip(na, nb):
        if x == y:
            continue
        if not (x.startswith("~") and y.startswith("~")):
            return False
        fx, fy = float(x[1:]), float(y[1:])
        if fx == 0.0 or fy == 0.0 or fx * fy < 0 or max(fx / fy, fy / fx) > APPROX_FACTOR:
            return False
    return True


def settling_trial(rmse: list[list[float]], factor: float = 2.0) -> int | None:
    """The first trial from which every joint stays within ``factor`` × its final RMSE."""
    final = rmse[-1]
    for k in range(len(rmse)):
        if all(all(r[j] <= factor * final[j] for j in range(len(final))) for r in rmse[k:]):
            return k
    return None


# ----------------------------------------------------------------------------- generators


def gen_settling(run: Runner) -> str:
    """RMSE per trial of the default experiment, deg and encoder counts."""
    s = run.summary("sim")
    rmse = [_rmse_deg(s, k) for k in range(len(s["iterations"]))]
    rows = ["| k | j1 | j2 | j3 | j4 |", "|---|---|---|---|---|"]
    for k, r in enumerate(rmse):
        rows.append(f"| {k} | " + " | ".join(f"{_fmt(x)} ({_counts(x):.2f})" for x in r) + " |")
    k_s = settling_trial(rmse)
    final_counts = [_counts(x) for x in rmse[-1]]
    text = (
        f"`ilcrig sim` (defaults: `no-ilc-id`, path 1, 0.25 s, `ruckig`, no disturbance, {len(rmse)} trials), "
        f"RMSE in degrees (in encoder counts of {DEG_PER_COUNT:.3g}°):\n\n" + "\n".join(rows) + "\n\n"
        f"Settled (every joint within 2× of its final RMSE from then on) at k = {k_s}; the final RMSE is "
        f"{min(final_counts):.2f}–{max(final_counts):.2f} encoder counts.\n"
    )
    return text


def gen_transports(run: Runner) -> str:
    """Final RMSE and digest with feed-forward tables against cyclic PDOs."""
    rows = ["| `--ff-transport` | final RMSE per joint, deg (encoder counts) | `trace_sha256` |", "|---|---|---|"]
    for transport in ("table", "pdo"):
        s = run.summary("sim", "--ff-transport", transport)
        r = _rmse_deg(s, len(s["iterations"]) - 1)
        cells = ", ".join(f"{_fmt(x)} ({_counts(x):.1f})" for x in r)
        rows.append(f"| `{transport}` | {cells} | `{s['trace_sha256'][:16]}…` |")
    return "`ilcrig sim --ff-transport table|pdo` (default experiment, 10 trials):\n\n" + "\n".join(rows) + "\n"


LAW_ORDER = ("pd-ilc", "pd-ilc-q", "pd-ol", "p-ol", "d-ilc", "q-ilc", "no-ilc", "no-ilc-id", "cno-ilc", "adjoint-ilc")


def gen_laws(run: Runner) -> str:
    """Per built-in law on the default experiment: the check's verdict and the measured result."""
    rows = [
        "| law | check: spectral radius, 200 trials | RMSE trial 0 → 9, deg (max over joints) | settled at k | `trace_sha256` |",
        "|---|---|---|---|---|",
    ]
    for law in LAW_ORDER:
        s = run.summary("sim", "--law", law)
        c = s["convergence_check"]
        rmse = [_rmse_deg(s, k) for k in range(len(s["iterations"]))]
        k_s = settling_trial(rmse)
        if c.get("checked") is False:
            verdict = "not checked (no linear map)"
        else:
            verdict = f"{c['rho_max']:.4f}, " + ("bounded" if c["long_bounded"] else "**grows again**")
        rows.append(
            f"| `{law}` | {verdict} | {_fmt(max(rmse[0]))} → {_fmt(max(rmse[-1]))} | "
            f"{k_s if k_s is not None else '—'} | `{s['trace_sha256'][:16]}…` |"
        )
    return "`ilcrig sim --law LAW` (path 1, 0.25 s, `ruckig`, 10 trials):\n\n" + "\n".join(rows) + "\n"


def gen_bus_fit(run: Runner) -> str:
    """The cyclic exchange of ``--ff-transport pdo`` against the fieldbus (``bus.cyclic``)."""
    code = (
        "import json\nfrom bus.cyclic import cyclic_bus_fit\nrows = []\n"
        "for label, r, t in [('rig default: RPDO 0x607A+0x60B2 (6 B), TPDO 0x6064+0x6077 (6 B)', 6, 6),"
        " ('TPDO + statusword 0x6041 (8 B)', 6, 8), ('full 8-byte RPDO and TPDO', 8, 8)]:\n"
        "    for b in (1_000_000, 500_000):\n"
        "        rows.append([label, cyclic_bus_fit(0.001, b, rpdo_bytes=r, tpdo_bytes=t).as_dict()])\n"
        "print(json.dumps(rows))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True, timeout=120)
    rows = [
        "| mapping | Mbit/s | bits per period | load at 1 kHz | fits (margin) | highest rate that fits "
        "| bit rate needed at 1 kHz |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, f in json.loads(out.stdout):
        fits = f"yes (+{f['margin_percent']:.1f} %)" if f["fits"] else f"no ({f['margin_percent']:.1f} %)"
        rows.append(
            f"| {label} | {f['bitrate_bps'] / 1e6:g} | {f['bits_nominal']}–{f['bits_worst_case']} | "
            f"{f['load_percent_nominal']:.1f}–{f['load_percent_worst_case']:.1f} % | {fits} | "
            f"{f['max_rate_hz']:.0f} Hz | {f['min_bitrate_bps'] / 1e6:.3f} Mbit/s |"
        )
    first = json.loads(out.stdout)[0][1]
    half = json.loads(out.stdout)[1][1]
    stuffless = 100.0 - first["load_percent_nominal"]
    return (
        "\n".join(rows) + "\n\n"
        f"So the rig's mapping fits {first['bitrate_bps'] / 1e6:g} Mbit/s at 1 kHz with {first['margin_percent']:.1f} % "
        f"worst-case margin ({stuffless:.0f} % without stuffing), and {half['bitrate_bps'] / 1e6:g} Mbit/s only up to "
        f"{half['max_rate_hz']:.0f} Hz.\n"
    )


def gen_bus_time(run: Runner) -> str:
    """What the default experiment's traffic would take on real buses (``ilcrig run``'s ``bench.bus_time``)."""
    bt = run.summary("run")["bench"]["bus_time"]
    io, fb = bt["io"], bt["fieldbus"]
    between = fb["between_trials"]
    kinds = between["by_kind_per_trial"]
    rates = (1_000_000, 500_000)
    motion_s = between["trial_motion_s"]
    period_s = io["control_period_s"]

    def secs(bits: float, rate: int) -> str:
        return f"{bits / rate:.3f} s"

    def io_cell(rate: int) -> str:
        bits = io["worst_tick"]["bits"]
        cap = rate * period_s
        if bits <= cap:
            return f"{bits:.0f} bits of {cap:.0f}: {100 * bits / cap:.0f} %, fits"
        return f"{bits:.0f} bits of {cap:.0f}: does **not** fit, a tick needs {1e3 * bits / rate:.2f} ms"

    def between_cell(rate: int) -> str:
        t = between["bits_per_trial"] / rate
        share = 100 * motion_s / (motion_s + t)
        return f"{between['bits_per_trial']:.0f} bits, {t:.3f} s: cycle {motion_s + t:.3f} s ({share:.0f} % in motion)"

    hb = fb["during_trials"]["heartbeat_model"]
    rows = [
        "| | " + " | ".join(f"{r / 1e3:.0f} kbit/s" for r in rates) + " |",
        "|---|---|---|",
        "| io, per tick during trials (4 encoder + 4 torque frames) | " + " | ".join(io_cell(r) for r in rates) + " |",
        "| io, per trial: TRIAL_START + TRIAL_STOP | "
        + " | ".join(f"{io['control_bits_per_trial']:.0f} bits, {1e3 * io['control_bits_per_trial'] / r:.2f} ms" for r in rates)
        + " |",
        "| fieldbus during trials, what the experiment sends | "
        + " | ".join(f"{fb['during_trials']['experiment_bits_per_tick']} bits" for _ in rates)
        + " |",
        f"| fieldbus during trials, heartbeats ({hb['nodes']} nodes every {hb['period_ms']} ms; model), worst tick | "
        + " | ".join(f"{hb['worst_tick']['bits']} bits, {100 * hb['worst_tick']['bits'] / (r * period_s):.0f} %" for r in rates)
        + " |",
    ]
    for kind, v in kinds.items():
        rows.append(
            f"| between trials, per trial: {kind} | "
            + " | ".join(f"{v['bits']:.0f} bits, {secs(v['bits'], r)}" for r in rates)
            + " |"
        )
    rows.append("| **between trials, per trial** | " + " | ".join(between_cell(r) for r in rates) + " |")
    once = fb["once_per_run"]["bits"]
    rows.append(
        "| once per run: configuration, gains, reference tables, enabling | "
        + " | ".join(f"{once:.0f} bits, {secs(once, r)}" for r in rates)
        + " |"
    )
    return (
        f"`ilcrig run` (default experiment: N = {io['ticks'] // between['trials']}, Ts = {period_s * 1e3:g} ms, 4 drives), "
        "its `bench.bus_time` at both bit rates:\n\n" + "\n".join(rows) + "\n"
    )


def gen_torque_limit(run: Runner) -> str:
    """Where the joint torque limit binds (0.125 s cycles): unconstrained laws against ``cno-ilc``."""
    import numpy as np

    args = ("--cycle", "0.125", "--profile", "poly4567")
    rows = [
        "| law | peak \\|u\\| of the last trial's feed-forward, N·m | peak applied torque, N·m "
        "| final RMSE, deg (max over joints) |",
        "|---|---|---|---|",
    ]
    for law in ("no-ilc-id", "pd-ilc", "cno-ilc"):
        s = run.summary("sim", *args, "--law", law)
        last = len(s["iterations"]) - 1
        with np.load(run.folder("sim", *args, "--law", law) / "trials" / f"trial-{last:05d}.npz") as z:
            u_peak = float(np.max(np.abs(z["feedforward_nm"])))
        applied = max(float(x) for x in s["iterations"][last]["peak_torque_nm"])
        rows.append(f"| `{law}` | {u_peak:.1f} | {applied:.1f} | {_fmt(max(_rmse_deg(s, last)))} |")
    return "`ilcrig sim --cycle 0.125 --profile poly4567 --law LAW` (10 trials):\n\n" + "\n".join(rows) + "\n"


def gen_no_weight(run: Runner) -> str:
    """The norm-optimal weight against the cycle time (``no-ilc``, 4-5-6-7 law, path 1)."""
    rows = ["| weight w, cycle | mean RMSE k = 3 | k = 5 | k = 9 | worst MaxE at k = 9 |", "|---|---|---|---|---|"]
    small = run.config_file("no_weight_1e-9.toml", "[gains]\nno_weight = 1e-9\n")
    for label, extra in (("1e-9", ("--config", small)), ("1e-5 (default)", ())):
        # w = 1e-9 makes the norm-optimal solve ill-conditioned: its figures are stated approximately
        fmt = _approx if extra else _fmt
        for cycle in ("0.5", "0.25"):
            s = run.summary("sim", "--law", "no-ilc", "--profile", "poly4567", "--cycle", cycle, *extra)
            mean = [sum(_rmse_deg(s, k)) / 4 for k in (3, 5, 9)]
            maxe = max(float(x) for x in s["iterations"][9]["max_abs_deg"])
            rows.append(f"| {label}, {cycle} s | " + " | ".join(fmt(x) for x in mean) + f" | {fmt(maxe)} |")
    return (
        "`ilcrig sim --law no-ilc --profile poly4567 --cycle C` (path 1, 10 trials; w = 1e-9 through a config file "
        "with `[gains] no_weight = 1e-9`), RMSE and MaxE in degrees. At w = 1e-9 the solve is ill-conditioned and "
        "its figures depend on the CPU's BLAS kernels (up to 50 % apart between two x86-64 machines measured): they "
        f"are given to one digit (`~`) and checked within a factor of {APPROX_FACTOR:g}:\n\n" + "\n".join(rows) + "\n"
    )


def gen_montecarlo(run: Runner) -> str:
    """The Monte Carlo table of ``examples/montecarlo.toml``'s sweep report (100 plants per law)."""
    with tempfile.TemporaryDirectory(prefix="ilcrig-docfigures-mc-") as tmp:
        argv = ["sweep", "--spec", "examples/montecarlo.toml", "--workers", "2", "--no-dashboard", "--out", tmp + "/mc"]
        proc = subprocess.run(
            [sys.executable, "-P", "-m", "host.cli", *argv], cwd=ROOT, capture_output=True, text=True, timeout=1800
        )
        if proc.returncode != 0:
            raise RuntimeError(f"ilcrig {' '.join(argv)} exited {proc.returncode}: {proc.stderr[-500:].strip()}")
        report = (Path(tmp) / "mc" / "report.md").read_text()
    section = report.split("## Monte Carlo", 1)[1]
    table = [line for line in section.split("## Points", 1)[0].splitlines() if line.startswith("|")]
    return "\n".join(table) + "\n\n(final RMSE in degrees, median, 95th percentile and worst over the plants)\n"


@dataclass(frozen=True)
class Generator:
    fn: Callable[[Runner], str]
    #: seconds it takes on a quiet 2-core machine (the test runs them all)
    cost_s: float


GENERATORS: dict[str, Generator] = {
    "settling": Generator(gen_settling, 10),
    "transports": Generator(gen_transports, 20),
    "laws": Generator(gen_laws, 90),
    "bus-fit": Generator(gen_bus_fit, 2),
    "bus-time": Generator(gen_bus_time, 30),
    "torque-limit": Generator(gen_torque_limit, 20),
    "no-weight": Generator(gen_no_weight, 15),
    "montecarlo": Generator(gen_montecarlo, 60),
}


# ----------------------------------------------------------------------------- checking


@dataclass
class Finding:
    file: str
    what: str

    def __str__(self) -> str:
        return f"{self.file}: {self.what}"


def sim_args_of(cmd: str) -> list[str]:
    """The ``ilcrig sim`` arguments of a stated ``ilcrig sim|run …`` command line."""
    words = shlex.split(cmd)[2:]
    args: list[str] = []
    i = 0
    while i < len(words):
        w = words[i]
        name = w.split("=", 1)[0]
        if name in RUN_ONLY_OPTIONS:
            i += 1 + (RUN_ONLY_OPTIONS[name] if "=" not in w else 0)
            continue
        if name == "--out":
            i += 1 if "=" in w else 2
            continue
        args.append(w)
        i += 1
    return args


def check_digest_lines(run: Runner, files: list[Path]) -> list[Finding]:
    found: list[Finding] = []
    for path in files:
        for m in DIGEST_RE.finditer(path.read_text()):
            digest = run.summary("sim", *sim_args_of(m["cmd"]))["trace_sha256"]
            if not digest.startswith(m["hex"]):
                found.append(
                    Finding(str(path.relative_to(ROOT)), f"`{m['cmd'].strip()}` states {m['hex']}…, prints {digest[:16]}…")
                )
    return found


def regenerate(run: Runner, text: str, rel: str, findings: list[Finding], only: set[str] | None = None) -> str:
    """``text`` with its figure blocks (those named in ``only``, or all) regenerated; what differed
    is appended to ``findings``."""

    def repl(m: re.Match[str]) -> str:
        if only is not None and m["name"] not in only:
            return m.group(0)
        gen = GENERATORS.get(m["name"])
        if gen is None:
            findings.append(Finding(rel, f"unknown figures block {m['name']!r}"))
            return m.group(0)
        body = gen.fn(run)
        if same_figures(m["body"], body):
            return m.group(0)
        findings.append(Finding(rel, f"figures block {m['name']!r} differs from what its command gives now"))
        return m.group(1) + body + m.group(4)

    return BLOCK_RE.sub(repl, text)


def check(write: bool = False, only: set[str] | None = None) -> list[Finding]:
    """Every digest line and figure block of the documentation against its command."""
    run = Runner()
    findings: list[Finding] = []
    try:
        files = doc_files()
        if only is None or "digests" in only:
            findings += check_digest_lines(run, files)
        for path in files:
            rel = str(path.relative_to(ROOT))
            text = path.read_text()
            if only is not None:
                names = {m["name"] for m in BLOCK_RE.finditer(text)}
                if not names & only:
                    continue
            new = regenerate(run, text, rel, findings, only)
            if write and new != text:
                path.write_text(new)
    finally:
        run.close()
    return findings


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--write", action="store_true", help="rewrite the figure blocks in place")
    ap.add_argument("--only", default=None, help="comma-separated generator names (and/or 'digests')")
    a = ap.parse_args(argv)
    only = set(a.only.split(",")) if a.only else None
    findings = check(write=a.write, only=only)
    for f in findings:
        print(f)
    if a.write:
        return 0
    return 1 if findings else 0


if __name__ == "__main__":
    raise SystemExit(main())

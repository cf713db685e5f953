"""What the README and docs/ state is what the code does.

* Every digest line (``ilcrig sim …  # trace_sha256 0123abcd…``) and every generated figure block
  (``<!-- figures: NAME -->``) of README.md and docs/*.md is checked against the command that
  produces it (``scripts/docfigures.py``, which runs the commands).
* Every relative link of those files points to a file of the repository.
* The quickstart's test command is the one ``.ci/run`` runs.
"""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _docfigures() -> ModuleType:
    spec = importlib.util.spec_from_file_location("docfigures", ROOT / "scripts" / "docfigures.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["docfigures"] = mod
    spec.loader.exec_module(mod)
    return mod


docfigures = _docfigures()


def test_every_figure_block_names_a_generator_and_digest_lines_exist() -> None:
    names: set[str] = set()
    digest_lines = 0
    for path in docfigures.doc_files():
        text = path.read_text()
        names |= {m["name"] for m in docfigures.BLOCK_RE.finditer(text)}
        digest_lines += len(docfigures.DIGEST_RE.findall(text))
    assert names <= set(docfigures.GENERATORS), names - set(docfigures.GENERATORS)
    # the three digests the README promises (defaults, pdo, the paper's law) are among them
    assert digest_lines >= 3
    readme = (ROOT / "README.md").read_text()
    for cmd in ("ilcrig sim ", "ilcrig sim --ff-transport pdo", "ilcrig sim --law pd-ilc"):
        assert any(m["cmd"].strip() == cmd.strip() for m in docfigures.DIGEST_RE.finditer(readme)), cmd


def test_sim_args_of_drops_run_only_options() -> None:
    assert docfigures.sim_args_of("ilcrig run --ff-transport pdo --bus hub --realtime --out x") == ["--ff-transport", "pdo"]
    assert docfigures.sim_args_of("ilcrig sim --law=pd-ilc --rt-priority 0") == ["--law=pd-ilc"]


def test_settling_trial_is_the_first_from_which_every_joint_stays_within_twice_its_final() -> None:
    rmse = [[10.0, 10.0], [1.0, 3.0], [2.0, 1.9], [1.5, 1.0], [1.0, 1.0]]
    assert docfigures.settling_trial(rmse) == 2
    assert docfigures.settling_trial([[5.0], [1.0], [3.0], [1.0]]) == 3


@pytest.mark.slow
@pytest.mark.multiprocess
@pytest.mark.parametrize("name", ["digests", *docfigures.GENERATORS])
def test_digests_and_figures_the_docs_state_are_what_the_commands_give(name: str) -> None:
    """One check per generator (and one for the digest lines), each well inside the test timeout."""
    findings = docfigures.check(only={name})
    assert not findings, "\n".join(map(str, findings)) + "\n(run `python scripts/docfigures.py --write` for figure blocks)"


LINK_RE = re.compile(r"\]\((?!https?://|mailto:|#)(?P<target>[^)#\s]+)(?:#[^)]*)?\)")


def test_relative_links_of_readme_and_docs_point_to_files() -> None:
    broken = []
    for path in docfigures.doc_files():
        for m in LINK_RE.finditer(path.read_text()):
            if not (path.parent / m["target"]).exists():
                broken.append(f"{path.relative_to(ROOT)} -> {m['target']}")
    assert not broken, broken


def test_quickstart_test_command_is_what_ci_runs() -> None:
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    cmd = "python3 -m venv .venv && .venv/bin/pip install -q -e '.[test]' && .venv/bin/python -m pytest"
    assert cmd in readme and cmd in ci


@pytest.mark.parametrize("step", ["set-up", "fast tier"])
def test_ci_ends_when_the_readme_command_fails_at_any_of_its_steps(tmp_path: Path, step: str) -> None:
    """``.ci/run``'s set-up and fast-tier lines (``python3 -m venv … && pip … && pytest``) run under
    ``set -e``, which does not stop a script for a failed command inside an ``&&`` list unless it is
    the last one: a venv that could not be made (a killed ``ensurepip``) skipped the fast tier, and
    the run went on to the full tier as if it had passed. Each line, run as ``.ci/run`` runs it with
    a ``python3`` that fails, ends the script with that exit code and says which step failed."""
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    line = next(x for x in ci if x.startswith("python3 -m venv .venv && ") and f'"== {step} failed' in x)
    stub = tmp_path / "bin"
    stub.mkdir()
    (stub / "python3").write_text("#!/bin/sh\nexit 7\n")
    (stub / "python3").chmod(0o755)
    script = f"set -euo pipefail\n{line}\necho 'the next step'\n"
    env = {"PATH": f"{stub}:/usr/bin:/bin"}
    res = subprocess.run(["bash", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert (res.returncode, res.stdout) == (7, f"== {step} failed (exit code 7)\n")


def test_readme_is_short_and_tells_no_history() -> None:
    readme = (ROOT / "README.md").read_bytes()
    assert len(readme) < 20_000
    history = re.compile(r"\b[Ii]ssue \d+\b|\b[Mm]oved here from\b|\bbefore issue\b")
    told = []
    for pattern in ("*.md", "docs/*.md", "*/**/*.py", "*/**/*.md", "examples/**/*.toml", ".ci/*", "scripts/*"):
        for path in ROOT.glob(pattern):
            if ".venv" in path.parts or "build" in path.parts:
                continue
            if history.search(path.read_text(errors="replace")):
                told.append(str(path.relative_to(ROOT)))
    assert not told, f"files that tell the history of past work: {sorted(set(told))}"


PATH_RE = re.compile(r"(?<![\w/.-])((?:[\w.-]+/)+[\w.-]+\.(?:py|md|eds|dbc|c|pyi|toml|txt|yaml|cfg))")


def test_every_file_path_the_docs_name_exists() -> None:
    """A path like ``host/rig/launcher.py`` in the README or docs names a file of the repository
    (relative to the root or to the document); a path inside a package's own line of the layout
    (``path_files/example.toml`` under ``planning/``) is looked up in that package."""
    missing = []
    for path in docfigures.doc_files():
        for m in PATH_RE.finditer(path.read_text()):
            p = m.group(1)
            first = p.split("/")[0]
            if first.isupper() or first in ("runs", "tmp"):  # a placeholder (OUT/, RUN_DIR/) or a run folder
                continue
            if (ROOT / p).exists() or (path.parent / p).exists() or list(ROOT.glob(f"*/**/{p}")):
                continue
            missing.append(f"{path.relative_to(ROOT)}: {p}")
    assert not missing, missing


def test_every_benchmark_is_in_the_benchmarks_table() -> None:
    """docs/benchmarks.md lists every script of ``benchmarks/`` with what it measures."""
    text = (ROOT / "docs" / "benchmarks.md").read_text()
    listed = set(re.findall(r"^\| `benchmarks/([\w-]+\.py)` \|", text, re.M))
    scripts = {p.name for p in (ROOT / "benchmarks").glob("*.py") if not p.name.startswith("_")}
    assert scripts <= listed, sorted(scripts - listed)

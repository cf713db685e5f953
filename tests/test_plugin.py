"""The example plug-in (examples/ilcrig-law-example) installed into a fresh virtual environment, run
by name through the command line (``ilcrig sim`` and the multi-process ``ilcrig run``: equal
digests) and through the API.

The fresh venv sees this test's environment (ilcrig and its dependencies) through a ``.pth`` file
that adds its site-packages, and gets the plug-in by ``pip install --no-deps --no-build-isolation
--no-index``: nothing is downloaded."""

from __future__ import annotations

import json
import os
import signal
import site
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.multiprocess]

REPO = Path(__file__).resolve().parent.parent
PLUGIN = REPO / "examples" / "ilcrig-law-example"
EXP = ["--law", "leaky-p", "--law-options", "gain=0.8,forgetting=0.99", "--iterations", "2", "--cycle", "0.15"]


def _run(cmd: list[str], cwd: Path, timeout_s: float = 600.0) -> subprocess.CompletedProcess[str]:
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"{cmd} timed out:\n{out}\n{err}")
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


@pytest.fixture(scope="module")
def venv_python(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("venv")
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(root / "env")], check=True)
    py = root / "env" / "bin" / "python"
    purelib = subprocess.run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], check=True, capture_output=True, text=True
    ).stdout.strip()
    ours = [p for p in site.getsitepackages() + [site.getusersitepackages()] if Path(p).is_dir()]
    # this environment's site-packages (with their own .pth files: ilcrig's editable install) after the venv's
    (Path(purelib) / "zz_ilcrig_test_env.pth").write_text("".join(f"import site; site.addsitedir({p!r})\n" for p in ours))
    res = _run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index", str(PLUGIN)], cwd=root)
    assert res.returncode == 0, res.stdout + res.stderr
    return py


def test_plugin_runs_by_name_in_cli_and_api(venv_python: Path, tmp_path: Path) -> None:
    py = str(venv_python)
    laws = _run([py, "-m", "host.cli", "laws"], cwd=tmp_path)
    assert laws.returncode == 0 and "leaky-p" in laws.stdout and "example plug-in" in laws.stdout
    sim = _run([py, "-m", "host.cli", "sim", *EXP, "--out", str(tmp_path / "sim")], cwd=tmp_path)
    assert sim.returncode == 0, sim.stdout + sim.stderr
    assert "convergence check: spectral radius" in sim.stdout  # the plug-in gives its map: checked
    rig = _run([py, "-m", "host.cli", "run", *EXP, "--bus", "hub", "--out", str(tmp_path / "rig")], cwd=tmp_path)
    assert rig.returncode == 0, rig.stdout + rig.stderr
    s_sim = json.loads((tmp_path / "sim" / "summary.json").read_text())
    s_rig = json.loads((tmp_path / "rig" / "summary.json").read_text())
    assert s_rig["mode"] == "rig" and s_rig["completed"] and s_sim["convergence_check"]["checked"] is True
    assert s_rig["trace_sha256"] == s_sim["trace_sha256"]
    assert s_sim["config"]["law"] == "leaky-p" and s_sim["config"]["law_options"] == {"gain": 0.8, "forgetting": 0.99}
    api = _run(
        [
            py,
            "-c",
            textwrap.dedent(
                """
                import ilcrig
                res = ilcrig.Experiment(law="leaky-p", law_options={"gain": 0.8, "forgetting": 0.99},
                                        iterations=2, cycle_s=0.15).run()
                print(res.digest)
                """
            ),
        ],
        cwd=tmp_path,
    )
    assert api.returncode == 0, api.stderr
    assert api.stdout.strip() == s_sim["trace_sha256"]
    bad = _run(
        [py, "-m", "host.cli", "sim", "--law", "leaky-p", "--law-options", "forgetting=2", "--out", str(tmp_path / "x")],
        cwd=tmp_path,
    )
    assert (
        bad.returncode == 2 and bad.stderr.strip() == "ilcrig: error: law 'leaky-p': option forgetting must be in (0, 1], got 2.0"
    )

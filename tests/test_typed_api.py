"""A user's script that imports ``ilcrig`` type-checks with mypy against the installed package.

The packages ship ``py.typed`` (PEP 561): the test installs the project as a user gets it from a
wheel (``pip install --target``, not the editable checkout), then runs mypy on a script in a
folder of its own, with that installation as the only place ``ilcrig`` can come from. A correct
script passes; a script that misuses the API is reported (so the types are really seen, not taken
as ``Any``).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

GOOD = textwrap.dedent(
    """
    import numpy as np
    import ilcrig

    exp = ilcrig.Experiment(law="pd-ilc", iterations=2, cycle_s=0.15)
    res: ilcrig.Results = exp.run()
    rmse: np.ndarray = res.rmse_deg
    last: ilcrig.TrialResult = res.final
    print(rmse.shape, last.error_rad.shape, res.digest, ilcrig.available_laws())
    """
)

BAD = textwrap.dedent(
    """
    import ilcrig

    wrong: int = ilcrig.load
    """
)


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The project installed from its sources into a folder (no dependencies: they are this venv's)."""
    target = tmp_path_factory.mktemp("site")
    # a copy of the sources: the build writes build/ beside them, never into the checkout
    src = tmp_path_factory.mktemp("src") / "ilcrig"
    keep = ("pyproject.toml", "setup.py", "README.md", "LICENSE", "bus", "firmware_model", "host", "plant", "ilcrig")
    shutil.copytree(ROOT, src, ignore=lambda d, names: [n for n in names if Path(d) == ROOT and n not in keep] + ["__pycache__"])
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--target", str(target), str(src)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (target / "ilcrig" / "py.typed").exists()
    return target


def _mypy(script: str, site: Path, where: Path) -> subprocess.CompletedProcess[str]:
    (where / "user_script.py").write_text(script)
    env = {k: v for k, v in os.environ.items() if k not in ("MYPYPATH", "PYTHONPATH")}
    # the installed copy is where the interpreter finds ilcrig (and the checkout is not: cwd elsewhere)
    env["PYTHONPATH"] = str(site)
    return subprocess.run(
        [sys.executable, "-m", "mypy", "--no-incremental", "--cache-dir", os.devnull]
        + ["--python-executable", sys.executable, "user_script.py"],
        cwd=where,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.mark.slow
def test_a_users_script_type_checks_against_the_installed_package(installed: Path, tmp_path: Path) -> None:
    proc = _mypy(GOOD, installed, tmp_path)
    assert "py.typed" not in proc.stdout and "library stubs" not in proc.stdout, proc.stdout
    assert proc.returncode == 0, proc.stdout + proc.stderr


@pytest.mark.slow
def test_a_misuse_of_the_api_is_reported(installed: Path, tmp_path: Path) -> None:
    proc = _mypy(BAD, installed, tmp_path)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "user_script.py:4: error: Incompatible types in assignment" in proc.stdout, proc.stdout

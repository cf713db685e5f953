"""Plug-in laws and the law registry.

The example plug-in (examples/ilcrig-law-example) installed into a fresh virtual environment, run by
name through the command line (``ilcrig sim`` and the multi-process ``ilcrig run``: equal digests)
and through the API (slow).  The fresh venv sees this test's environment (ilcrig and its
dependencies) through a ``.pth`` file that adds its site-packages, and gets the plug-in by ``pip
install --no-deps --no-build-isolation --no-index``: nothing is downloaded.

The registry's rules, with entry points of fake distributions (``importlib.metadata`` distributions
in a temporary folder, handed to the registry through its discovery function): the project's names
cannot be taken by a plug-in or a registered class, two distributions cannot claim one name, and
where a law came from is in summary.json; the one checked wrapper every law runs in.
"""

from __future__ import annotations

import json
import logging
import site
import subprocess
import sys
import textwrap
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest
from cli_util import run_in_session

import ilcrig
from host.learning import registry
from host.learning.laws.checked import LawError, build_law
from host.learning.laws.constrained import ConstrainedNormOptimal
from host.learning.laws.table import PROJECT_LAWS

REPO = Path(__file__).resolve().parent.parent
PLUGIN = REPO / "examples" / "ilcrig-law-example"
EXP = ["--law", "leaky-p", "--law-options", "gain=0.8,forgetting=0.99", "--iterations", "2", "--cycle", "0.15"]


def _run(cmd: list[str], cwd: Path, timeout_s: float = 600.0) -> subprocess.CompletedProcess[str]:
    return run_in_session(cmd, timeout_s, cwd)


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


@pytest.mark.slow
@pytest.mark.multiprocess
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


# ------------------------------------------------------------------ the registry's rules


def _dist(root: Path, name: str, version: str, entry_points: dict[str, str]) -> metadata.Distribution:
    """A distribution ``name`` ``version`` declaring ``entry_points`` (name → value) in the group ilcrig.laws."""
    info = root / f"{name.replace('-', '_')}-{version}.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n")
    (info / "entry_points.txt").write_text("[ilcrig.laws]\n" + "".join(f"{k} = {v}\n" for k, v in entry_points.items()))
    return metadata.PathDistribution(info)


@pytest.fixture
def installed(monkeypatch: pytest.MonkeyPatch, tmp_path: Path):
    """``installed(dist, ...)``: the registry sees exactly the entry points of these distributions."""
    monkeypatch.setattr(registry, "_WARNED", set())

    def install(*dists: metadata.Distribution) -> None:
        eps = [ep for d in dists for ep in d.entry_points if ep.group == registry.ENTRY_POINT_GROUP]
        monkeypatch.setattr(registry, "discover_entry_points", lambda: eps)

    return install


def test_a_plugin_claiming_a_project_name_is_an_error_naming_its_distribution(
    installed, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    installed(_dist(tmp_path, "evil-laws", "1.2", {"cno-ilc": "evil_laws:Law", "evil-p": "evil_laws:P"}))
    caplog.set_level(logging.WARNING, logger=registry.__name__)
    for _ in range(3):
        with pytest.raises(ilcrig.InputError, match=r"plug-in law 'cno-ilc' of distribution 'evil-laws' 1\.2 .*project law"):
            registry.law_names()
        with pytest.raises(ilcrig.InputError, match="'evil-laws'"):
            registry.law_class("evil-p")  # the installation is refused, not just the one name
    with pytest.raises(ilcrig.InputError, match="'evil-laws'"):
        ilcrig.available_laws()
    # the project's law is never shadowed and still resolves
    assert registry.law_class("cno-ilc") is ConstrainedNormOptimal
    assert registry.law_source("cno-ilc") == {"name": "cno-ilc", "source": "built-in"}
    warnings = [r for r in caplog.records if "evil-laws" in r.getMessage()]
    assert len(warnings) == 1 and warnings[0].levelno == logging.WARNING  # once per cause, not per lookup


def test_two_plugins_claiming_one_name_is_an_error_naming_both(installed, tmp_path: Path) -> None:
    installed(
        _dist(tmp_path / "a", "laws-a", "1.0", {"fast-ilc": "laws_a:Fast"}),
        _dist(tmp_path / "b", "laws-b", "2.0", {"fast-ilc": "laws_b:Fast"}),
    )
    with pytest.raises(ilcrig.InputError, match="'fast-ilc' is claimed by two distributions") as err:
        registry.check_law_name("fast-ilc")
    assert "'laws-a' 1.0" in str(err.value) and "'laws-b' 2.0" in str(err.value) and "\n" not in str(err.value)


def test_a_plugin_resolves_and_says_where_it_came_from(installed, tmp_path: Path) -> None:
    installed(_dist(tmp_path, "good-laws", "0.3", {"half-p-plugin": f"{__name__}:HalfP"}))
    assert registry.law_names()[: len(PROJECT_LAWS)] == tuple(PROJECT_LAWS)
    assert "half-p-plugin" in registry.law_names() and registry.law_class("half-p-plugin") is HalfP
    assert registry.law_source("half-p-plugin") == {
        "name": "half-p-plugin",
        "source": "plug-in",
        "distribution": "good-laws",
        "version": "0.3",
        "entry_point": f"{__name__}:HalfP",
    }
    assert registry.law_source(f"{__name__}:HalfP") == {
        "name": f"{__name__}:HalfP",
        "source": "module",
        "module": __name__,
        "class": "HalfP",
    }


def test_register_law_refuses_a_project_name_and_honours_the_class_name(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(registry, "_REGISTERED", {})
    for name in ("pd-ilc", "cno-ilc", "adjoint-ilc"):
        with pytest.raises(ilcrig.InputError, match=f"law '{name}': the name of a project law"):
            ilcrig.register_law(HalfP, name)

    class Shadow(HalfP):
        name = "no-ilc-id"

    with pytest.raises(ilcrig.InputError, match="'no-ilc-id': the name of a project law"):
        ilcrig.register_law(Shadow)  # its own name attribute is the name it asks for
    assert ilcrig.register_law(HalfP) == "half-p" and registry.registered_here("half-p")
    assert registry.law_source("half-p") == {"name": "half-p", "source": "registered", "module": __name__, "class": "HalfP"}


def test_law_source_is_in_the_summary_of_ilcrig_sim(tmp_path: Path) -> None:
    from host.cli import main

    assert main(["sim", "--law", "pd-ol", "--iterations", "1", "--cycle", "0.15", "--out", str(tmp_path / "a")]) == 0
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["law_source"] == {"name": "pd-ol", "source": "built-in"}
    law = f"{__name__}:HalfP"
    assert main(["sim", "--law", law, "--iterations", "1", "--cycle", "0.15", "--out", str(tmp_path / "b")]) == 0
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert summary["law_source"] == {"name": law, "source": "module", "module": __name__, "class": "HalfP"}


# ------------------------------------------------------------------ the one checked wrapper


class HalfP:
    """u_{k+1} = u_k + 0.5·Lp·e_k (e led by ``shift`` samples, none here): a protocol law defined in a
    test module (tests/test_api.py's FixedGainLaw is this law with a one-sample lead)."""

    name = "half-p"
    description = "half the learning P gain"
    shift = 0

    def __init__(self, ctx: ilcrig.LawContext) -> None:
        self.lp = 0.5 * ctx.gains.lp

    def update(self, trial: ilcrig.TrialData) -> np.ndarray:
        return trial.feedforward_nm + self.lp * ilcrig.signals.lead(trial.error_rad, self.shift)


class Broken(HalfP):
    """A law whose code fails, returns a wrong shape or a non-finite table, as ``mode`` says."""

    mode = "raise"

    def update(self, trial: ilcrig.TrialData) -> np.ndarray:
        if self.mode == "raise":
            raise KeyError("no such joint")
        if self.mode == "shape":
            return trial.feedforward_nm[:-1]
        return np.full_like(trial.feedforward_nm, np.inf)


def _ctx() -> ilcrig.LawContext:
    from host.learning.gains import GainSpec, resolve_gains

    m = np.tile(np.diag([0.12, 0.11, 0.12, 0.11])[None], (20, 1, 1))
    gains = resolve_gains(GainSpec(), np.full(4, 0.115), 1e-3)
    return ilcrig.LawContext(gains=gains, ts_s=1e-3, model=ilcrig.ClosedLoopModel(m, gains.kp, gains.kd, 1e-3))


def test_every_law_runs_in_one_checked_wrapper(monkeypatch: pytest.MonkeyPatch) -> None:
    ctx = _ctx()
    z = np.zeros((20, 4))
    data = ilcrig.TrialData(3, z, z + 1e-3, z, z, 1e-3)
    project = build_law("pd-ol", ctx)
    module = build_law(f"{__name__}:HalfP", ctx)
    assert type(project) is type(module)  # one wrapper, whatever the law's kind
    assert module.name == "half-p" and module.source["source"] == "module" and not module.check().checked
    np.testing.assert_array_equal(module.update(data), 0.5 * ctx.gains.lp * 1e-3 + z)
    broken = build_law(f"{__name__}:Broken", ctx)
    with pytest.raises(LawError, match=r"law half-p failed in update after trial 3: KeyError") as err:
        broken.update(data)
    assert isinstance(err.value.__cause__, KeyError) and err.value.__cause__.__traceback__ is not None
    monkeypatch.setattr(Broken, "mode", "shape")
    with pytest.raises(LawError, match=r"returned shape \(19, 4\), expected \(20, 4\)"):
        broken.update(data)
    monkeypatch.setattr(Broken, "mode", "inf")
    with pytest.raises(FloatingPointError, match="non-finite"):
        broken.update(data)

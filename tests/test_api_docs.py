"""Every code block of docs/api.md runs as it is, top to bottom in one namespace, in a fresh
working directory: the ``python`` blocks in a quick test, and with them the ``py`` blocks (they
start the multi-process rig) in a slow one."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

DOC = Path(__file__).resolve().parent.parent / "docs" / "api.md"


def python_blocks(text: str) -> list[str]:
    """The bodies of the blocks fenced ```python … ```."""
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_docs_api_examples_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    blocks = python_blocks(DOC.read_text(encoding="utf-8"))
    assert len(blocks) >= 6
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {"__name__": "__docs__"}
    for i, code in enumerate(blocks):
        exec(compile(code, f"docs/api.md block {i + 1}", "exec"), namespace)  # noqa: S102 - the documentation's own code
    out = capsys.readouterr().out
    assert "iterations must be between 1 and 1000, got 0" in out
    assert "['learning', 'auxiliary', 'auxiliary', 'learning']" in out


def all_blocks(text: str) -> list[str]:
    """The bodies of the blocks fenced ```python … ``` or ```py … ```, in the document's order."""
    return re.findall(r"^```(?:python|py)\n(.*?)^```", text, flags=re.S | re.M)


@pytest.mark.slow
@pytest.mark.multiprocess
def test_docs_api_examples_run_with_the_rig(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    blocks = all_blocks(DOC.read_text(encoding="utf-8"))
    assert len(blocks) > len(python_blocks(DOC.read_text(encoding="utf-8")))
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {"__name__": "__docs__"}
    for i, code in enumerate(blocks):
        exec(compile(code, f"docs/api.md block {i + 1}", "exec"), namespace)  # noqa: S102 - the documentation's own code
    assert (tmp_path / "rig-a" / "summary.json").is_file()


def test_table2_example_uses_the_api_alone(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    import runpy

    script = DOC.parent.parent / "examples" / "table2.py"
    imports = {line.split()[1] for line in script.read_text().splitlines() if line.startswith(("import ", "from "))}
    assert imports <= {"__future__", "argparse", "numpy", "ilcrig"}  # nothing of the internals
    monkeypatch.setattr("sys.argv", [str(script), "--iterations", "2"])
    runpy.run_path(str(script), run_name="__main__")
    out = capsys.readouterr().out
    assert "PD-ILC    ilcrig" in out and "D-ILC     ilcrig" in out and "PD-ILC below D-ILC on every joint:" in out


def test_every_public_name_is_documented() -> None:
    import ilcrig

    text = DOC.read_text(encoding="utf-8")
    missing = [name for name in ilcrig.__all__ if f"`{name}`" not in text and f"ilcrig.{name}" not in text]
    assert not missing, f"names of ilcrig.__all__ not in docs/api.md: {missing}"

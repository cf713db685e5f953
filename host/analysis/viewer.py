"""``ilcrig view``: a run's ``recording.rrd`` in the Rerun viewer — the native one, or Rerun's web
viewer served on loopback when the native one cannot start — or the command to open it printed (no
viewer installed).  :func:`view_run` takes typed arguments (not the parsed command line);
:func:`viewer_command` and :func:`display_available` are shared with the live view (:mod:`host.analysis.live_view`).
Imports no rerun (the viewer is a child process).

* A display and a viewer: the native viewer is started and watched for :data:`NATIVE_SETTLE_S`;
  only one still running then is reported as opened.
* No display, or a native viewer that exited at once (graphics it cannot use): Rerun's web viewer
  (``rerun RRD --web-viewer``), every listener bound to 127.0.0.1 on a free port; its URL is printed
  and the command serves it until Ctrl-C / SIGTERM, which stop the viewer too.  A web viewer that
  does not come up within :data:`WEB_START_S` is said as such (exit 1); never "opened".

May import: ``bus`` (exit codes).
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TextIO

from bus.exit_codes import EXIT_ERROR, EXIT_INTERRUPTED, EXIT_OK, EXIT_TERMINATED, EXIT_USAGE

logger = logging.getLogger(__name__)

__all__ = ["display_available", "view_run", "viewer_command", "web_viewer_args", "NATIVE_SETTLE_S", "WEB_START_S"]

#: seconds a native viewer must keep running to count as opened
NATIVE_SETTLE_S = 3.0
#: seconds to wait for the web viewer's URL
WEB_START_S = 30.0
#: the only address the web viewer listens on
LOOPBACK = "127.0.0.1"
#: the line Rerun writes when its web viewer is up (the address to open is the second URL)
_WEB_URL = re.compile(r"Hosting a web-viewer at (\S+) - connect at (\S+)")


def _rerun_version() -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("rerun-sdk")
    except PackageNotFoundError:
        return None


def viewer_command() -> list[str] | None:
    """The command that starts the Rerun viewer here: ``rerun`` on PATH, the one next to this
    Python, or ``python -m rerun``; None if rerun-sdk is not installed."""
    exe = shutil.which("rerun")
    if exe:
        return [exe]
    sibling = Path(sys.executable).parent / "rerun"
    if sibling.is_file() and os.access(sibling, os.X_OK):
        return [str(sibling)]
    from importlib.util import find_spec

    if find_spec("rerun_cli") is not None or find_spec("rerun") is not None:
        return [sys.executable, "-m", "rerun"]
    return None


def display_available() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def web_viewer_args(rrd: Path) -> list[str]:
    """The viewer's arguments that serve ``rrd`` in the web viewer, every listener (HTTP and gRPC)
    on 127.0.0.1 and a free port."""
    return [str(rrd), "--web-viewer", "--bind", LOOPBACK, "--web-viewer-port", "0", "--port", "0"]


def _native(cmd: list[str], rrd: Path, log: Path) -> str | None:
    """Start the native viewer; None if it runs after :data:`NATIVE_SETTLE_S`, else why not."""
    try:
        with open(log, "wb") as fh:
            proc = subprocess.Popen([*cmd, str(rrd)], stdin=subprocess.DEVNULL, stdout=fh, stderr=fh, start_new_session=True)
    except OSError as exc:
        return f"cannot start the native viewer {cmd[0]}: {exc.strerror or exc}"
    try:
        code = proc.wait(timeout=NATIVE_SETTLE_S)
    except subprocess.TimeoutExpired:
        return None
    return f"the native viewer exited at once (exit code {code}; its output: {log})"


#: the viewer's log line that gives the web viewer's URL (read from its output) is at this level
_URL_LOG_DIRECTIVE = "re_sdk::web_viewer=info"


def _web_viewer_env() -> dict[str, str]:
    """This environment with the viewer's URL line logged whatever ``RUST_LOG`` says (a recording
    made in this process, or the user, may have set it to ``off``): the directive for that one
    module is added to the user's."""
    env = dict(os.environ)
    env["RUST_LOG"] = ",".join(d for d in (env.get("RUST_LOG", "").strip(), _URL_LOG_DIRECTIVE) if d)
    return env


def _serve_web(cmd: list[str], rrd: Path, log: Path, out: TextIO, err: TextIO) -> int:
    """Serve ``rrd`` in the web viewer on loopback until Ctrl-C / SIGTERM; print its URL."""
    try:
        with open(log, "wb") as fh:
            proc = subprocess.Popen(
                [*cmd, *web_viewer_args(rrd)],
                stdin=subprocess.DEVNULL,
                stdout=fh,
                stderr=fh,
                start_new_session=True,
                env=_web_viewer_env(),
            )
    except OSError as exc:
        err.write(f"ilcrig view: cannot start the web viewer {cmd[0]}: {exc.strerror or exc}\n")
        return EXIT_ERROR
    old_term = signal.getsignal(signal.SIGTERM)
    terminated = False

    def on_term(signum: int, frame: object) -> None:
        nonlocal terminated
        terminated = True
        raise KeyboardInterrupt

    try:
        signal.signal(signal.SIGTERM, on_term)
    except ValueError:  # not the main thread
        old_term = None
    try:
        deadline = time.monotonic() + WEB_START_S
        url = None
        while url is None:
            m = _WEB_URL.search(log.read_text(errors="replace"))
            if m:
                url = m.group(2)
                break
            if proc.poll() is not None or time.monotonic() > deadline:
                why = f"exited (exit code {proc.returncode})" if proc.returncode is not None else "did not start"
                err.write(f"ilcrig view: Rerun's web viewer {why} within {WEB_START_S:.0f} s (its output: {log})\n")
                return EXIT_ERROR
            time.sleep(0.1)
        out.write(f"ilcrig view: {rrd} in Rerun's web viewer on {LOOPBACK}: open {url}\n")
        out.write("ilcrig view: serving until Ctrl-C\n")
        out.flush()
        code = proc.wait()
        err.write(f"ilcrig view: the web viewer ended (exit code {code})\n")
        return EXIT_OK if code == 0 else EXIT_ERROR
    except KeyboardInterrupt:
        return EXIT_TERMINATED if terminated else EXIT_INTERRUPTED
    finally:
        _end_group(proc)
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)


def _end_group(proc: subprocess.Popen[bytes]) -> None:
    """End the viewer and whatever it started (its own session: ``rerun`` may run the viewer binary
    as a child): SIGTERM to the group, SIGKILL after 5 s."""
    for sig, wait_s in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except (ProcessLookupError, PermissionError):
            break
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            proc.poll()
            try:
                os.killpg(proc.pid, 0)
            except (ProcessLookupError, PermissionError):
                return
            time.sleep(0.05)
    proc.poll()


def _why_no_recording(folder: Path) -> str:
    """What the run folder's summary says of a run without a recording ("": no summary there)."""
    from host.experiment.outputs import SUMMARY_NAME, end_reason_of, read_summary

    s = read_summary(folder)
    if s is None:
        return ""
    how = end_reason_of(s) or "still running"
    mark = s.get("interrupted")
    if isinstance(mark, dict) and mark.get("signal"):
        how = f"interrupted by {mark['signal']}"
    elif s.get("faults"):
        how = f"fault: {s['faults'][0].get('kind', '?')}"
    kept = len(s["iterations"])
    return f": the run kept {kept} trial{'s' if kept != 1 else ''} ({how}); summary: {folder / SUMMARY_NAME}"


def view_run(run_dir: str | Path, *, stdout: TextIO | None = None, stderr: TextIO | None = None) -> int:
    """``ilcrig view RUN_DIR``: open ``RUN_DIR/recording.rrd`` in the native viewer, or serve it in
    the web viewer on loopback (module docstring), or say how to open it.

    :returns: 0 (the native viewer running, the web viewer served and ended, or the command
        printed), 1 if no viewer could be started, 2 if there is no recording, 130 / 143 when the
        web viewer's serving was ended by Ctrl-C / SIGTERM.
    """
    out = stdout if stdout is not None else sys.stdout
    err = stderr if stderr is not None else sys.stderr
    p = Path(run_dir)
    rrd = p if p.suffix == ".rrd" else p / "recording.rrd"
    if not rrd.is_file():
        err.write(f"ilcrig: error: no recording at {rrd}{_why_no_recording(rrd.parent)}\n")
        return EXIT_USAGE
    rrd = rrd.resolve()
    cmd = viewer_command()
    if cmd is None:
        ver = _rerun_version()
        pin = f"rerun-sdk=={ver}" if ver else "rerun-sdk"
        out.write(
            "ilcrig view: no Rerun viewer installed; open the recording where one is:\n"
            f"  rerun {rrd}\n  (viewer: pip install {pin})\n"
        )
        return EXIT_OK
    logs = Path(tempfile.mkdtemp(prefix="ilcrig-view-"))
    if display_available():
        why = _native(cmd, rrd, logs / "native.log")
        if why is None:
            out.write(f"ilcrig view: opened {rrd} in the Rerun viewer ({' '.join(cmd)})\n")
            shutil.rmtree(logs, ignore_errors=True)  # the viewer keeps its open log; nothing is left behind
            return EXIT_OK
    else:
        why = "no display ($DISPLAY / $WAYLAND_DISPLAY unset)"
    err.write(f"ilcrig view: {why}; falling back to Rerun's web viewer on {LOOPBACK}\n")
    code = _serve_web(cmd, rrd, logs / "web.log", out, err)
    if code != EXIT_ERROR:  # a failure's output stays where its message said
        shutil.rmtree(logs, ignore_errors=True)
    return code

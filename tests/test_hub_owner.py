"""A hub only its owner can use (bus/transports/hub/owner.py, addresses.py, server.py): the
default socket in a private per-user folder, sockets 0600 whatever the umask, a squatted folder or
socket refused with a line naming its owner, every client checking the hub's user before it sends
anything, the hub refusing a client of another user in the handshake (Unix socket and loopback
TCP), ``ilcrig hub`` errors like every command's.

The cases with a second user run it as ``nobody`` (``setpriv --reuid=65534 --regid=65534
--clear-groups``, the system's ``/usr/bin/python3`` with the standard library only: the project's
interpreter may live where ``nobody`` cannot read); they need root and are skipped otherwise."""

from __future__ import annotations

import os
import shutil
import socket
import stat
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from bus.transports.hub.owner import HubOwnerError, check_peer, peer_uid, private_dir, runtime_dir
from bus.transports.hub.wire import MAGIC_NO, ROLE_MEMBER, hello

REPO = Path(__file__).resolve().parent.parent
NOBODY = 65534
SYSTEM_PYTHON = "/usr/bin/python3"


def as_nobody(*argv: str, **kw: object) -> list[str]:
    return ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", *argv]


needs_second_user = pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which("setpriv") is None or not os.access(SYSTEM_PYTHON, os.X_OK),
    reason="needs root, setpriv and /usr/bin/python3 to act as a second user (nobody)",
)


@pytest.fixture
def public_tmp() -> Iterator[Path]:
    """A world-writable sticky folder in /tmp, like /tmp itself (removed after the test)."""
    import tempfile

    d = Path(tempfile.mkdtemp(prefix="ilcrig-owner-test-", dir="/tmp"))
    os.chmod(d, 0o1777)
    try:
        yield d
    finally:
        shutil.rmtree(d, ignore_errors=True)


def hub_cli(*args: str, env: dict[str, str] | None = None, umask: int | None = None) -> subprocess.Popen[str]:
    """``python -m host.cli hub --ready ARGS`` (its stdin closes it)."""

    def pre() -> None:
        if umask is not None:
            os.umask(umask)

    return subprocess.Popen(
        [sys.executable, "-m", "host.cli", "hub", "--ready", "--exit-on-stdin-eof", *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env={**os.environ, **(env or {})},
        preexec_fn=pre,
    )


@pytest.fixture
def hubs() -> Iterator[list[subprocess.Popen[str]]]:
    started: list[subprocess.Popen[str]] = []
    yield started
    for p in started:
        if p.poll() is None:
            assert p.stdin is not None
            p.stdin.close()
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def ready(p: subprocess.Popen[str]) -> list[str]:
    assert p.stdout is not None
    line = p.stdout.readline()
    assert line.startswith("ILCRIG-HUB-READY"), (line, p.stderr.read() if p.stderr else "")
    return line.split()[1:]


# ---------------------------------------------------------------------------------------
# one user
# ---------------------------------------------------------------------------------------


def test_a_private_folder_is_made_0700_and_checked(tmp_path: Path) -> None:
    d = private_dir(tmp_path / "mine")
    assert stat.S_IMODE(d.stat().st_mode) == 0o700 and d.stat().st_uid == os.geteuid()
    assert private_dir(d) == d  # again: fine
    os.chmod(d, 0o755)
    with pytest.raises(HubOwnerError, match=r"its mode is 0755, others may enter it; `chmod 700"):
        private_dir(d)
    (tmp_path / "link").symlink_to(d)
    with pytest.raises(HubOwnerError, match="it is a link or not a folder"):
        private_dir(tmp_path / "link")


def test_the_default_address_is_in_the_users_folder(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from bus.transports.hub.addresses import default_hub_address

    monkeypatch.delenv("ILCRIG_HUB", raising=False)
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)
    assert default_hub_address() == f"unix:{tmp_path}/ilcrig-{os.geteuid()}/hub.sock"
    xdg = tmp_path / "run-user"
    xdg.mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(xdg))
    assert runtime_dir() == xdg / "ilcrig" and default_hub_address() == f"unix:{xdg}/ilcrig/hub.sock"


def test_peer_of_a_socketpair_is_this_user() -> None:
    a, b = socket.socketpair()
    with a, b:
        assert peer_uid(a) == os.geteuid()
        check_peer(a, "the hub")


def test_hub_errors_are_one_line_and_exit_2(tmp_path: Path) -> None:
    for args, text in (
        (["hub", "--listen", "bogus"], "ilcrig: error: unknown hub address 'bogus'; use unix:/path or tcp:127.0.0.1:PORT\n"),
        (["hub", "--listen", "tcp:8.8.8.8:1"], "ilcrig: error: refusing non-loopback hub address '8.8.8.8'"),
    ):
        res = subprocess.run([sys.executable, "-m", "host.cli", *args], capture_output=True, text=True, cwd=REPO, timeout=60)
        assert res.returncode == 2 and res.stderr.startswith(text) and len(res.stderr.splitlines()) == 1, res.stderr
    res = subprocess.run(
        [sys.executable, "-m", "host.cli", "hub", "--bus-time", "x"], capture_output=True, text=True, cwd=REPO, timeout=60
    )
    assert res.returncode == 2 and res.stderr.startswith("ilcrig: error: ") and len(res.stderr.splitlines()) == 1


def test_sockets_are_0600_whatever_the_umask(tmp_path: Path, hubs: list[subprocess.Popen[str]]) -> None:
    env = {"TMPDIR": str(tmp_path), "XDG_RUNTIME_DIR": ""}
    p = hub_cli(env=env, umask=0)
    hubs.append(p)
    assert ready(p) == [f"unix:{tmp_path}/ilcrig-{os.geteuid()}/hub.sock"]
    folder = tmp_path / f"ilcrig-{os.geteuid()}"
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert stat.S_IMODE((folder / "hub.sock").stat().st_mode) == 0o600
    q = hub_cli("--listen", f"unix:{tmp_path}/other.sock", umask=0)
    hubs.append(q)
    ready(q)
    assert stat.S_IMODE((tmp_path / "other.sock").stat().st_mode) == 0o600


# ---------------------------------------------------------------------------------------
# a second user
# ---------------------------------------------------------------------------------------

#: connects to a Unix socket and tells what happened (stdlib only: runs as nobody)
CONNECT = """
import socket, sys
s = socket.socket(socket.AF_UNIX if sys.argv[1].startswith('/') else socket.AF_INET)
try:
    s.connect(sys.argv[1] if sys.argv[1].startswith('/') else ('127.0.0.1', int(sys.argv[1])))
except OSError as e:
    print('connect', e.errno); sys.exit()
s.sendall(bytes.fromhex(sys.argv[2]))
s.settimeout(10)
print('reply', s.recv(300).hex())
"""

#: a squatter's 'hub': accepts one connection and tells how many bytes it was sent
SQUAT = """
import os, socket, sys
s = socket.socket(socket.AF_UNIX); s.bind(sys.argv[1]); os.chmod(sys.argv[1], 0o777); s.listen(1)
print('listening', flush=True)
c, _ = s.accept(); c.settimeout(5); got = b''
try:
    while True:
        d = c.recv(4096)
        if not d: break
        got += d
except OSError:
    pass
print('received', len(got), flush=True)
"""


@needs_second_user
def test_another_user_cannot_reach_a_default_hub_at_umask_000(public_tmp: Path, hubs: list[subprocess.Popen[str]]) -> None:
    p = hub_cli(env={"TMPDIR": str(public_tmp), "XDG_RUNTIME_DIR": ""}, umask=0)
    hubs.append(p)
    sock = ready(p)[0].removeprefix("unix:")
    res = subprocess.run(
        as_nobody(SYSTEM_PYTHON, "-c", CONNECT, sock, hello(ROLE_MEMBER, "io").hex()), capture_output=True, text=True
    )
    assert res.stdout.strip() == "connect 13", res  # EACCES: the folder is root's, 0700


@needs_second_user
def test_a_squatted_folder_is_refused(public_tmp: Path) -> None:
    folder = public_tmp / f"ilcrig-{os.geteuid()}"
    subprocess.run(as_nobody("mkdir", "-m", "700", str(folder)), check=True)
    res = subprocess.run(
        [sys.executable, "-m", "host.cli", "hub"],
        capture_output=True,
        text=True,
        cwd=REPO,
        env={**os.environ, "TMPDIR": str(public_tmp), "XDG_RUNTIME_DIR": ""},
        timeout=60,
    )
    assert res.returncode == 2 and len(res.stderr.splitlines()) == 1
    assert res.stderr.startswith(
        f"ilcrig: error: refusing the hub folder {folder}: it belongs to nobody (uid {NOBODY}), not to you (uid 0): "
        "someone may be squatting it"
    )
    assert folder.stat().st_uid == NOBODY  # never changed


@needs_second_user
def test_a_client_tells_nothing_to_a_hub_of_another_user(public_tmp: Path) -> None:
    """Another user binds the path first: root's drive refuses it before sending a byte, in one
    line naming that user; a hub of root refuses to bind over that user's socket."""
    path = public_tmp / "hub.sock"
    squat = subprocess.Popen(as_nobody(SYSTEM_PYTHON, "-c", SQUAT, str(path)), stdout=subprocess.PIPE, text=True)
    try:
        assert squat.stdout is not None and squat.stdout.readline() == "listening\n"
        res = subprocess.run(
            [sys.executable, "-m", "host.cli", "drive", "--node", "1", "--bus", "hub", "--hub", f"unix:{path}"],
            capture_output=True,
            text=True,
            cwd=REPO,
            timeout=60,
        )
        assert res.returncode == 2, res.stderr
        assert res.stderr == (
            f"ilcrig: error: the hub at unix:{path} runs as nobody (uid {NOBODY}), not as you (root, uid 0) or root: "
            "refusing to talk to it (another user's hub, or someone impersonating yours)\n"
        )
        assert squat.stdout.readline() == "received 0\n"  # not a byte of the handshake
        bind = subprocess.run(
            [sys.executable, "-m", "host.cli", "hub", "--listen", f"unix:{path}"],
            capture_output=True,
            text=True,
            cwd=REPO,
            timeout=60,
        )
        assert bind.returncode == 2 and bind.stderr.startswith(
            f"ilcrig: error: refusing {path}: the socket belongs to nobody (uid {NOBODY}), not to you"
        )
    finally:
        squat.kill()
        squat.wait()


@needs_second_user
@pytest.mark.parametrize("where", ["unix", "tcp"])
def test_the_hub_refuses_a_client_of_another_user(public_tmp: Path, hubs: list[subprocess.Popen[str]], where: str) -> None:
    """Even where another user reaches the socket (a socket opened up by hand, loopback TCP), the
    hub refuses them in the handshake, saying why."""
    listen = f"unix:{public_tmp}/open.sock" if where == "unix" else "tcp:127.0.0.1:0"
    p = hub_cli("--listen", listen)
    hubs.append(p)
    addr = ready(p)[0]
    if where == "unix":
        target = addr.removeprefix("unix:")
        os.chmod(target, 0o777)  # opened up by hand: the owner check still holds
    else:
        target = addr.rsplit(":", 1)[1]
    res = subprocess.run(
        as_nobody(SYSTEM_PYTHON, "-c", CONNECT, target, hello(ROLE_MEMBER, "io").hex()), capture_output=True, text=True
    )
    kind, _, payload = res.stdout.strip().partition(" ")
    assert kind == "reply", res
    reply = bytes.fromhex(payload)
    assert reply.startswith(MAGIC_NO)
    text = reply[5 : 5 + reply[4]].decode()
    assert text.startswith(f"a client runs as nobody (uid {NOBODY}), not as you (root, uid 0) or root: refusing"), text
    # its own user is served as before
    from bus.transports.hub.stats import query_hub_stats

    assert query_hub_stats(addr) == {}

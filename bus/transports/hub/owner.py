"""Who may use a hub: only the user who runs it (and root), on both ends of every connection.

This module owns the hub's owner rule:

* :func:`runtime_dir` / :func:`private_dir` — where a hub's socket lives by default: a folder of
  this user alone (``$XDG_RUNTIME_DIR/ilcrig``, else ``<temp folder>/ilcrig-<uid>``), made with
  mode 0700 and then checked without following a link (``O_NOFOLLOW``, ``fstat``): a folder, owned
  by this user, not reachable by anyone else.  A folder there that someone else owns (a squatter
  in the world-writable temp folder), a link or a folder others can enter is refused with
  :class:`HubOwnerError`, never used or changed;
* :func:`private_socket_mode` — a listening Unix socket's file gets mode 0600 whatever the umask
  (``fchmod`` of the socket before ``bind``: Linux makes the file with the socket's mode masked by
  the umask; ``chmod`` after it as well);
* :func:`peer_uid` — the user id of the process at the other end of a connection: ``SO_PEERCRED``
  on a Unix socket, the owner of the peer's socket in ``/proc/net/tcp[6]`` on loopback TCP, None
  on TCP to another machine (``--allow-remote``: unauthenticated, documented as such);
* :func:`check_peer` — the rule itself: the peer runs as this user or as root, else
  :class:`HubOwnerError` saying who it is.  Clients check the hub before they send anything
  (:func:`bus.transports.hub.addresses.connect`); the hub checks every client when it accepts it
  (:class:`bus.transports.hub.server.HubServer`) and refuses a stranger in the handshake's words.
"""

from __future__ import annotations

import ipaddress
import logging
import os
import socket
import stat
import struct
import tempfile
from pathlib import Path

from bus.peer import peer_cred
from bus.transports.hub.wire import HubAddressError

logger = logging.getLogger(__name__)

__all__ = [
    "RUNTIME_DIR_NAME",
    "HubOwnerError",
    "check_peer",
    "peer_uid",
    "private_dir",
    "private_socket_mode",
    "runtime_dir",
    "user_name",
]

#: the folder of this user's hubs inside ``$XDG_RUNTIME_DIR``
RUNTIME_DIR_NAME = "ilcrig"


class HubOwnerError(HubAddressError, PermissionError):
    """A hub's folder or socket belongs to someone else, or the process at the other end of a
    connection runs as another user (one line saying who)."""


def user_name(uid: int) -> str:
    """``name`` of ``uid`` (``uid N`` when it has none)."""
    try:
        import pwd

        return f"{pwd.getpwuid(uid).pw_name}"
    except (ImportError, KeyError):
        return f"uid {uid}"


def runtime_dir() -> Path:
    """This user's folder for hub sockets: ``$XDG_RUNTIME_DIR/ilcrig`` when that variable names a
    folder of this user, else ``<temp folder>/ilcrig-<uid>`` (not made here: :func:`private_dir`)."""
    xdg = os.environ.get("XDG_RUNTIME_DIR", "").strip()
    if xdg:
        try:
            st = os.stat(xdg)
            if stat.S_ISDIR(st.st_mode) and st.st_uid == os.geteuid():
                return Path(xdg) / RUNTIME_DIR_NAME
        except OSError:
            pass
    return Path(tempfile.gettempdir()) / f"ilcrig-{os.geteuid()}"


def private_dir(path: str | Path, *, create: bool = True) -> Path:
    """``path`` as a folder of this user alone: made with mode 0700 if missing (``create``), then
    checked without following a link.

    :raises HubOwnerError: it is a link or not a folder, another user owns it, or others may enter
        or write it (it is never changed: someone may be squatting it)
    """
    p = Path(path)
    me = os.geteuid()
    if create:
        try:
            os.mkdir(p, 0o700)
        except FileExistsError:
            pass
        except OSError as err:
            raise HubOwnerError(f"cannot make the hub's private folder {p}: {err.strerror or err}") from None
    try:
        fd = os.open(p, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as err:
        what = "it is a link or not a folder" if os.path.islink(p) or os.path.exists(p) else (err.strerror or str(err))
        raise HubOwnerError(f"refusing the hub folder {p}: {what}; remove it or give another address (--hub)") from None
    try:
        st = os.fstat(fd)
    finally:
        os.close(fd)
    if st.st_uid != me:
        raise HubOwnerError(
            f"refusing the hub folder {p}: it belongs to {user_name(st.st_uid)} (uid {st.st_uid}), not to you "
            f"(uid {me}): someone may be squatting it; remove it or give another address (--hub, $ILCRIG_HUB)"
        )
    if st.st_mode & 0o077:
        raise HubOwnerError(
            f"refusing the hub folder {p}: its mode is {stat.S_IMODE(st.st_mode):04o}, others may enter it; "
            f"`chmod 700 {p}` or remove it"
        )
    return p


def private_socket_mode(sock: socket.socket) -> None:
    """Before ``bind``: the socket file gets mode 0600 whatever the umask (see the module docstring)."""
    try:
        os.fchmod(sock.fileno(), 0o600)
    except OSError as err:  # pragma: no cover - Linux allows it on a socket
        logger.debug("fchmod of the hub socket before bind: %s", err)


def _proc_net_uid(local: tuple[str, int], remote: tuple[str, int]) -> int | None:
    """The uid owning the TCP socket with local address ``local`` and remote ``remote`` (from
    ``/proc/net/tcp`` and ``tcp6``), None if not found."""

    def hexaddr(host: str, port: int) -> set[str]:
        ip = ipaddress.ip_address(host.split("%")[0])
        forms = set()
        if ip.version == 4:
            forms.add(f"{struct.unpack('<I', ip.packed)[0]:08X}:{port:04X}")
            mapped = ipaddress.IPv6Address("::ffff:" + str(ip)).packed
            forms.add("".join(f"{w:08X}" for w in struct.unpack("<4I", mapped)) + f":{port:04X}")
        else:
            forms.add("".join(f"{w:08X}" for w in struct.unpack("<4I", ip.packed)) + f":{port:04X}")
        return forms

    want_local, want_remote = hexaddr(*local), hexaddr(*remote)
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            with open(table, encoding="ascii") as fh:
                next(fh, None)
                for line in fh:
                    fields = line.split()
                    if len(fields) > 7 and fields[1] in want_local and fields[2] in want_remote:
                        return int(fields[7])
        except OSError:
            continue
    return None


def peer_uid(sock: socket.socket) -> int | None:
    """The user id of the process at the other end of the connected ``sock`` (see the module
    docstring); None where it cannot be known (TCP to another machine)."""
    if sock.family == socket.AF_UNIX:
        cred = peer_cred(sock)
        return None if cred is None else cred[1]
    peer, here = sock.getpeername()[:2], sock.getsockname()[:2]
    if not ipaddress.ip_address(str(peer[0]).split("%")[0]).is_loopback:
        return None
    # the peer's socket: its local address is our remote one and the other way round
    return _proc_net_uid((str(peer[0]), int(peer[1])), (str(here[0]), int(here[1])))


def check_peer(sock: socket.socket, what: str) -> None:
    """The process at the other end of ``sock`` runs as this user or as root, or cannot be known
    (TCP to another machine).

    :param what: who the peer is, for the message (``the hub at unix:/…``, ``a client``)
    :raises HubOwnerError: it runs as another user (or its user cannot be found on loopback TCP)
    """
    me = os.geteuid()
    try:
        uid = peer_uid(sock)
    except OSError as err:
        raise HubOwnerError(f"{what}: cannot tell which user runs it ({err.strerror or err})") from None
    if uid is None:
        if sock.family != socket.AF_UNIX and ipaddress.ip_address(str(sock.getpeername()[0]).split("%")[0]).is_loopback:
            raise HubOwnerError(f"{what}: cannot tell which user runs it (not in /proc/net/tcp)")
        return  # another machine (--allow-remote): unauthenticated
    if uid not in (me, 0):
        raise HubOwnerError(
            f"{what} runs as {user_name(uid)} (uid {uid}), not as you ({user_name(me)}, uid {me}) or root: "
            "refusing to talk to it (another user's hub, or someone impersonating yours)"
        )


def check_socket_file(path: str) -> None:
    """A Unix socket file this user may remove or bind over: a socket (not a link) owned by this
    user or root.

    :raises HubOwnerError: anything else (someone else's socket, a link, a regular file)
    """
    st = os.lstat(path)
    if not stat.S_ISSOCK(st.st_mode):
        raise HubOwnerError(f"refusing {path}: it is not a socket (a {_kind(st.st_mode)}); remove it or choose another address")
    if st.st_uid not in (os.geteuid(), 0):
        raise HubOwnerError(
            f"refusing {path}: the socket belongs to {user_name(st.st_uid)} (uid {st.st_uid}), not to you: "
            "another user's hub, or someone squatting the path; choose another address"
        )


def _kind(mode: int) -> str:
    if stat.S_ISLNK(mode):
        return "link"
    if stat.S_ISDIR(mode):
        return "folder"
    return "file" if stat.S_ISREG(mode) else "special file"

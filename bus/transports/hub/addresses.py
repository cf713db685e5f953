"""Hub addresses: where a hub listens and how a client reaches it.

This module owns :class:`HubAddress`, :func:`parse_address`, :func:`parse_channel`,
:func:`default_hub_address`, :func:`connect`, :func:`listen_socket` and the loopback rule: a TCP address that is not
loopback is refused (:class:`~bus.transports.hub.wire.NonLoopbackAddressError`) unless the caller
passes ``allow_remote=True`` (``ilcrig hub --allow-remote``, ``--allow-remote`` of the roles) to
span machines; a wildcard address (all interfaces) is refused even then.  The owner rule
(:mod:`bus.transports.hub.owner`) applies on both sides: the default address is a socket in this
user's private folder, a listening socket file has mode 0600, a stale socket file is removed only
when it is this user's, and :func:`connect` checks that the hub runs as this user (or root) before
anything is sent.

Channels
    One hub serves several logical buses. The channel string is ``<address>#<bus name>``, e.g.
    ``unix:/tmp/rig/hub.sock#io`` or ``tcp:127.0.0.1:29536#fieldbus``; without ``#`` the bus is
    ``default``. A bare path (``/tmp/x.sock``) means ``unix:``.
"""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import os
import socket
from dataclasses import dataclass
from typing import Any

from bus.transports.hub.owner import check_peer, check_socket_file, private_dir, private_socket_mode, runtime_dir
from bus.transports.hub.wire import HubAddressError, HubAddressInUseError, NonLoopbackAddressError

DEFAULT_BUS_NAME = "default"
MAX_BUS_NAME_BYTES = 64

#: environment variable naming the hub address used when none is given
HUB_ENV: str = "ILCRIG_HUB"

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class HubAddress:
    """Where a hub listens: ``unix`` (``path``) or ``tcp`` (loopback ``host``, ``port``)."""

    kind: str
    path: str = ""
    host: str = ""
    port: int = 0

    def __str__(self) -> str:
        if self.kind == "unix":
            return f"unix:{self.path}"
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"tcp:{host}:{self.port}"

    @property
    def family(self) -> socket.AddressFamily:
        if self.kind == "unix":
            return socket.AF_UNIX
        return socket.AF_INET6 if ":" in self.host else socket.AF_INET

    @property
    def sockaddr(self) -> Any:
        return self.path if self.kind == "unix" else (self.host, self.port)


def _require_loopback(host: str, port: int, allow_remote: bool = False) -> str:
    """Resolve ``host`` and return a numeric loopback address (any one address when
    ``allow_remote``, but never a wildcard).

    :raises NonLoopbackAddressError: empty or wildcard host, or (without ``allow_remote``) any
        resolved address not loopback
    """
    if not host:
        raise NonLoopbackAddressError("the hub listens on loopback only; an empty host means all interfaces")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as err:
        raise HubAddressError(f"cannot resolve hub host {host!r}: {err}") from err
    addrs = [str(info[4][0]) for info in infos]
    if allow_remote and addrs:
        if any(ipaddress.ip_address(a.split("%")[0]).is_unspecified for a in addrs):
            raise NonLoopbackAddressError(
                f"refusing the non-loopback wildcard hub address {host!r} (all interfaces): name one interface's address"
            )
        return addrs[0]
    bad = [a for a in addrs if not ipaddress.ip_address(a.split("%")[0]).is_loopback]
    if bad or not addrs:
        raise NonLoopbackAddressError(
            f"refusing non-loopback hub address {host!r} (resolves to {', '.join(addrs)}); "
            "use 127.0.0.1, ::1, localhost or a unix: path (or --allow-remote to span machines)"
        )
    return addrs[0]


def parse_address(text: str, allow_remote: bool = False) -> HubAddress:
    """Parse ``unix:/path``, a bare path, ``tcp:HOST:PORT`` or ``tcp:[v6]:PORT``.

    :param allow_remote: accept a TCP host that is not loopback (explicit opt-in)
    :raises NonLoopbackAddressError: a TCP host that is not loopback (without ``allow_remote``)
    :raises HubAddressError: anything else malformed
    """
    if not text:
        raise HubAddressError("empty hub address")
    if text.startswith("unix:"):
        path = text[5:]
        if not path:
            raise HubAddressError("unix: address without a path")
        return HubAddress("unix", path=path)
    if text.startswith("tcp:"):
        rest = text[4:]
        if rest.startswith("["):
            host, sep, port_s = rest[1:].partition("]:")
        else:
            host, sep, port_s = rest.rpartition(":")
        if not sep:
            raise HubAddressError(f"tcp address needs HOST:PORT, got {text!r}")
        try:
            port = int(port_s)
        except ValueError as err:
            raise HubAddressError(f"bad TCP port in {text!r}") from err
        if not 0 <= port <= 65535:
            raise HubAddressError(f"TCP port out of range in {text!r}")
        return HubAddress("tcp", host=_require_loopback(host, port, allow_remote), port=port)
    if "/" in text or text.endswith(".sock"):
        return HubAddress("unix", path=text)
    raise HubAddressError(f"unknown hub address {text!r}; use unix:/path or tcp:127.0.0.1:PORT")


def parse_channel(channel: str, allow_remote: bool = False) -> tuple[HubAddress, str]:
    """Split ``<address>#<bus name>`` into (address, bus name); the name defaults to ``default``.

    :raises HubAddressError: malformed address or bus name
    """
    if not isinstance(channel, str):
        raise HubAddressError(f"hub channel must be a string, got {channel!r}")
    addr_text, sep, name = channel.rpartition("#")
    if not sep:
        addr_text, name = channel, DEFAULT_BUS_NAME
    if not name or len(name.encode()) > MAX_BUS_NAME_BYTES or any(c.isspace() for c in name):
        raise HubAddressError(f"bad bus name {name!r} in channel {channel!r}")
    return parse_address(addr_text, allow_remote), name


#: the socket's name in the user's private folder (:func:`bus.transports.hub.owner.runtime_dir`)
DEFAULT_SOCKET_NAME = "hub.sock"


def default_hub_address() -> str:
    """``$ILCRIG_HUB`` if set, else a socket in this user's private folder,
    e.g. ``unix:/run/user/1000/ilcrig/hub.sock`` or ``unix:/tmp/ilcrig-1000/hub.sock``
    (:func:`bus.transports.hub.owner.runtime_dir`; the hub makes the folder, mode 0700)."""
    env = os.environ.get(HUB_ENV, "").strip()
    if env:
        return env
    return f"unix:{runtime_dir() / DEFAULT_SOCKET_NAME}"


def connect(addr: HubAddress, timeout_s: float) -> socket.socket:
    """A stream socket connected to the hub at ``addr`` (``TCP_NODELAY`` for TCP), whose process
    runs as this user or root (checked before anything is sent: :func:`bus.transports.hub.owner.check_peer`).

    :raises HubOwnerError: the hub runs as another user
    :raises OSError: nobody listens there
    """
    sock = socket.socket(addr.family, socket.SOCK_STREAM)
    try:
        sock.settimeout(timeout_s)
        sock.connect(addr.sockaddr)
        if addr.kind == "tcp":
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        check_peer(sock, f"the hub at {addr}")
    except BaseException:
        sock.close()
        raise
    return sock


def listen_socket(addr: HubAddress) -> tuple[socket.socket, HubAddress]:
    """A non-blocking stream socket listening on ``addr`` (an already parsed, so checked, address)
    and the address it is bound to (TCP port 0 replaced by the port picked). The default address's
    folder is made private first (:func:`bus.transports.hub.owner.private_dir`); a Unix socket file
    of this user nobody listens on any more is removed; the socket file gets mode 0600.

    :raises HubOwnerError: the folder or an old socket file at the path is someone else's
    :raises HubAddressInUseError: a live hub already listens on the Unix path
    :raises OSError: the address cannot be bound
    """
    if addr.kind == "unix":
        if os.path.dirname(os.path.abspath(addr.path)) == str(runtime_dir()):
            private_dir(runtime_dir())
        _clear_stale_unix_path(addr.path)
    sock = socket.socket(addr.family, socket.SOCK_STREAM)
    try:
        if addr.kind == "tcp":
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        else:
            private_socket_mode(sock)
        sock.bind(addr.sockaddr)
        if addr.kind == "unix":
            os.chmod(addr.path, 0o600)
        sock.listen(64)
        sock.setblocking(False)
    except BaseException:
        sock.close()
        raise
    if addr.kind == "unix":
        return sock, addr
    host, port = sock.getsockname()[:2]
    return sock, HubAddress("tcp", host=host, port=port)


def _clear_stale_unix_path(path: str) -> None:
    """Remove the Unix socket file ``path`` when nobody listens on it.

    :raises HubAddressInUseError: someone does
    """
    if not os.path.lexists(path):
        return
    check_socket_file(path)
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.connect(path)
    except (ConnectionRefusedError, FileNotFoundError):
        logger.info("removing stale hub socket %s", path)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        return
    except OSError as err:
        raise HubAddressInUseError(f"cannot use {path}: {err}") from err
    finally:
        probe.close()
    raise HubAddressInUseError(f"a hub already listens on {path}")

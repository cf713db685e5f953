"""The process at the other end of a connected Unix socket (``SO_PEERCRED``).

This module owns :func:`peer_cred` and :func:`peer_pid`, the one reading of ``struct ucred`` of
the project: the hub checks who connects (:func:`bus.transports.hub.owner.peer_uid`), a hub member
finds the hub that carries its frames (:func:`bus.run_queue.carrier_pid`).

May import: the standard library only.
"""

from __future__ import annotations

import socket
import struct

__all__ = ["peer_cred", "peer_pid"]

#: ``struct ucred`` of SO_PEERCRED: pid, uid, gid
_UCRED = struct.Struct("3i")


def peer_cred(sock: socket.socket) -> tuple[int, int, int] | None:
    """pid, uid and gid of the process at the other end of ``sock`` (None: not a Unix socket, or a
    system without ``SO_PEERCRED``).

    :raises OSError: the socket cannot be asked (not connected, closed)
    """
    if sock.family != socket.AF_UNIX or not hasattr(socket, "SO_PEERCRED"):
        return None
    pid, uid, gid = _UCRED.unpack(sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _UCRED.size))
    return pid, uid, gid


def peer_pid(sock: socket.socket) -> int | None:
    """The pid of the process at the other end of ``sock`` (a hub on this machine), else None."""
    cred = peer_cred(sock)
    return cred[0] if cred is not None and cred[0] > 0 else None

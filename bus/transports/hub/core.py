"""The hub's C data plane: the adapter between :class:`bus.transports.hub.server.HubServer` and the
C extension :mod:`bus.transports.hub._hubcore`.

This module owns whether a hub moves its members' frames in C (:func:`core_built`,
:func:`hub_core_available`, :data:`HUB_CORE_ENV`), whether a member answers frames in C
(:func:`member_core`) and :class:`CoreSelector`, the selector of a hub
whose members the C core serves (:func:`new_core_selector`).

Data planes
    Where the C extension is built (``setup.py``; it needs a C compiler at install), a hub moves its
    members' frames in C: once a member's handshake is done, the core reads its records, counts
    them, routes them by the rules of :mod:`bus.transports.hub.routing` and writes them out, in one
    epoll loop that also reports the descriptors the Python side still serves (listen sockets,
    handshakes, stats queries, the wake pipe) to :meth:`HubServer.serve_forever`. Profiling the rig
    showed about two thirds of the Python hub's CPU in the interpreter, moving 24-byte records. A
    hub with frame faults or bus time, or started with ``ILCRIG_HUB_CORE=python``
    (:data:`HUB_CORE_ENV`), uses the pure-Python path (:mod:`bus.transports.hub.routing`); both
    behave the same (``tests/test_hub*.py`` run on both), :attr:`HubServer.data_plane` says which
    one a hub uses.
"""

from __future__ import annotations

import contextlib
import os
import select
import selectors
from collections.abc import Callable, Mapping
from types import ModuleType
from typing import Any

from bus.busload import bits_lookup
from bus.transports.hub.routing import Client
from bus.transports.hub.wire import BULK_HOLD_S, BULK_MAX_BYTES

_hubcore: ModuleType | None
try:  # the hub's data plane in C, built at install when a C compiler is there (setup.py)
    from bus.transports.hub import _hubcore
except ImportError:  # pragma: no cover - depends on the installation
    _hubcore = None

#: environment variable: ``python`` makes every hub of this process and its children use the pure-Python
#: data plane even where the C one (:mod:`bus.transports.hub._hubcore`) is built (comparisons, debugging)
HUB_CORE_ENV: str = "ILCRIG_HUB_CORE"


def core_built() -> bool:
    """The C extension :mod:`bus.transports.hub._hubcore` is built in this installation."""
    return _hubcore is not None


def hub_core_available() -> bool:
    """A hub started now (without frame faults or bus time) would move frames in C."""
    return _hubcore is not None and os.environ.get(HUB_CORE_ENV, "c").strip().lower() != "python"


def member_core() -> ModuleType | None:
    """The C extension for a member's side of the wire (:meth:`bus.transports.hub.client.HubBus.answer_frames`),
    None where it is not built or :data:`HUB_CORE_ENV` is ``python`` (then every member reads in Python)."""
    return _hubcore if hub_core_available() else None


class CoreSelector(selectors.BaseSelector):
    """The selector of a hub whose members the C core serves (:mod:`bus.transports.hub._hubcore`).

    The descriptors the Python side registers (listen sockets, the wake pipe, the watched
    descriptor, clients before and outside membership) are watched by the core's epoll and come
    back from :meth:`select` as usual; a member handed over with :meth:`adopt` is read, routed and
    written by the core, and only comes back when the core dropped it (``on_drop(client, refuse,
    reason)``, called from :meth:`select`).
    """

    def __init__(self, module: ModuleType, on_drop: Any, **core_args: Any) -> None:
        self._core = module.Core(**core_args)
        self._report_events: int = module.REPORT_EVENTS
        self._report_refuse: int = module.REPORT_REFUSE
        self._on_drop = on_drop
        self._keys: dict[int, selectors.SelectorKey] = {}
        self._members: dict[int, Client] = {}

    @staticmethod
    def _mask(events: int) -> int:
        return (select.EPOLLIN if events & selectors.EVENT_READ else 0) | (
            select.EPOLLOUT if events & selectors.EVENT_WRITE else 0
        )

    def register(self, fileobj: Any, events: int, data: Any = None) -> selectors.SelectorKey:
        fd = selectors._fileobj_to_fd(fileobj)  # type: ignore[attr-defined]
        if fd in self._keys or fd in self._members:
            raise KeyError(f"{fileobj!r} (fd {fd}) is already registered")
        key = selectors.SelectorKey(fileobj, fd, events, data)
        self._core.watch(fd, self._mask(events))
        self._keys[fd] = key
        return key

    def unregister(self, fileobj: Any) -> selectors.SelectorKey:
        fd = selectors._fileobj_to_fd(fileobj)  # type: ignore[attr-defined]
        key = self._keys.pop(fd)
        with contextlib.suppress(OSError, ValueError):
            self._core.unwatch(fd)
        return key

    def modify(self, fileobj: Any, events: int, data: Any = None) -> selectors.SelectorKey:
        fd = selectors._fileobj_to_fd(fileobj)  # type: ignore[attr-defined]
        old = self._keys[fd]
        key = selectors.SelectorKey(old.fileobj, fd, events, data)
        self._core.watch(fd, self._mask(events))
        self._keys[fd] = key
        return key

    def adopt(self, client: Client, bus: int, stamp_ns: int) -> None:
        """The core serves ``client`` (a member after its handshake) from now on, starting with the
        bytes it already sent (read at ``stamp_ns``) and the bytes still to be sent to it."""
        fd = client.sock.fileno()
        self._keys.pop(fd, None)
        self._core.add_member(
            fd, bus, client.echo, client.classic, client.bulk, bytes(client.inbuf), bytes(client.outbuf), stamp_ns
        )
        client.inbuf.clear()
        client.outbuf.clear()
        client.writing = False
        self._members[fd] = client

    def release(self, client: Client) -> None:
        """Take ``client`` back from the core (before its socket closes)."""
        with contextlib.suppress(OSError):
            fd = client.sock.fileno()
            if self._members.get(fd) is client:
                del self._members[fd]
                self._core.remove(fd)

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        ready: list[tuple[selectors.SelectorKey, int]] = []
        for fd, kind, value in self._core.poll(-1.0 if timeout is None else max(0.0, timeout)):
            if kind == self._report_events:
                key = self._keys.get(fd)
                if key is None:
                    continue
                events = 0
                if value & ~select.EPOLLIN:
                    events |= selectors.EVENT_WRITE
                if value & ~select.EPOLLOUT:
                    events |= selectors.EVENT_READ
                if key.events & events:
                    ready.append((key, key.events & events))
            else:
                client = self._members.pop(fd, None)
                if client is not None:
                    self._on_drop(client, kind == self._report_refuse, value)
        return ready

    def stats(self, bus: int, reset: bool) -> tuple[int, int, int, int, int, int]:
        """The core's counters of logical bus ``bus`` (index): frames, bits, bits worst case, FD frames,
        error frames, dropped members; ``reset`` zeroes the frame and bit counts afterwards."""
        counts: tuple[int, int, int, int, int, int] = self._core.stats(bus, reset)
        return counts

    def get_map(self) -> Mapping[Any, selectors.SelectorKey]:
        return {key.fileobj: key for key in self._keys.values()}

    def close(self) -> None:
        self._keys.clear()
        self._members.clear()
        self._core.close()


def new_core_selector(on_drop: Callable[[Client, bool, str], None], recv_chunk: int, max_outbuf: int) -> CoreSelector:
    """The selector of a hub whose members the C core serves (:func:`hub_core_available` must be
    true): ``on_drop(client, refuse, reason)`` is called for a member the core dropped; the core
    reads up to ``recv_chunk`` bytes at once and drops a member with more than ``max_outbuf``
    unsent bytes."""
    assert _hubcore is not None
    return CoreSelector(
        _hubcore,
        on_drop,
        bits=[bits_lookup(n, ext)[k] for ext in (False, True) for n in range(9) for k in (0, 1)],
        recv_chunk=recv_chunk,
        max_outbuf=max_outbuf,
        bulk_hold_s=BULK_HOLD_S,
        bulk_max_bytes=BULK_MAX_BYTES,
    )

"""Hub counters: what a hub counted on each logical bus, and how to ask a running hub for them.

This module owns :class:`HubChannelStats` (per logical bus: frames and bits, without and with
worst-case stuffing (:mod:`bus.busload`), FD and error frames, clients, connections, dropped
clients, and the bus's bitrates), its encoding in the hub's answer to a stats query
(:func:`encode_stats`) and the query itself (:func:`query_hub_stats`). Frames are counted as sent,
before frame faults or bus time act on them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

from bus.busload import BusLoadCounter
from bus.transports.hub.addresses import connect, parse_address, parse_channel
from bus.transports.hub.wire import MAGIC_OK, ROLE_STATS, ROLE_STATS_RESET, U32, HubError, hello, read_reply, recv_exact


@dataclass
class HubChannelStats:
    """What the hub counted on one logical bus since start (or the last reset)."""

    frames: int = 0
    bits: int = 0
    bits_worst_case: int = 0
    fd_frames: int = 0
    error_frames: int = 0
    clients: int = 0
    connections: int = 0
    dropped_clients: int = 0
    #: the logical bus's bitrates, bit/s (0 = no member gave one), set by the first member
    #: that joins the empty bus; a member asking for another one is refused
    bitrate: int = 0
    data_bitrate: int = 0

    def load(self) -> BusLoadCounter:
        """The classic-CAN frame and bit totals as a :class:`BusLoadCounter`."""
        return BusLoadCounter(self.frames, self.bits, self.bits_worst_case, self.fd_frames)

    def add_core_counts(self, counts: tuple[int, int, int, int, int, int]) -> None:
        """Add what the C core counted (frames, bits, bits worst case, FD frames, error frames,
        dropped members; :meth:`bus.transports.hub.core.CoreSelector.stats`)."""
        self.frames += counts[0]
        self.bits += counts[1]
        self.bits_worst_case += counts[2]
        self.fd_frames += counts[3]
        self.error_frames += counts[4]
        self.dropped_clients += counts[5]

    def reset_counts(self) -> None:
        """Zero the frame and bit counters (clients, connections and bitrates stay)."""
        self.frames = self.bits = self.bits_worst_case = self.fd_frames = self.error_frames = 0


def encode_stats(stats: dict[str, HubChannelStats]) -> bytes:
    """The hub's answer to a stats query: ``ILOK``, u32 n, n bytes JSON (bus name → counters)."""
    body = json.dumps({k: vars(v) for k, v in stats.items()}).encode()
    return MAGIC_OK + U32.pack(len(body)) + body


def query_hub_stats(address: str, reset: bool = False, timeout_s: float = 2.0) -> dict[str, HubChannelStats]:
    """Ask a running hub for its per-bus counters.

    :param address: the hub address (a channel string's ``#bus`` part is ignored)
    :param reset: zero the frame and bit counters after reading them
    :param timeout_s: connect and answer timeout, s
    :raises HubError: no hub, or a protocol error
    """
    addr = parse_channel(address)[0] if "#" in address else parse_address(address)
    try:
        sock = connect(addr, timeout_s)
    except OSError as err:
        raise HubError(f"cannot reach hub at {addr}: {err}") from err
    with sock:
        sock.sendall(hello(ROLE_STATS_RESET if reset else ROLE_STATS, ""))
        read_reply(sock)
        n = U32.unpack(recv_exact(sock, 4))[0]
        raw = json.loads(recv_exact(sock, n))
    return {name: HubChannelStats(**values) for name, values in raw.items()}

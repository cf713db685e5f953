"""Transport selection: which python-can interface carries each logical channel.

This module owns the two logical channels' bus configuration (docs/architecture.md §1, "Processes and
channels"): :class:`ChannelConfig` (one python-can bus), :func:`open_bus`,
:class:`TransportConfig` (``fieldbus`` + ``io``) and the factories :func:`auto_transport`,
:func:`hub_transport`, :func:`socketcan_transport`, :func:`udp_multicast_transport`,
:func:`virtual_transport`, :func:`can_config_transport`, :func:`transport_from_name`.
Code above ``bus/`` only ever receives a :class:`can.BusABC` from :func:`open_bus`.

Configuration precedence (python-can's, resolved in one place, :func:`resolve_bus_config`):
explicit ``ChannelConfig`` fields and kwargs > ``can.rc`` > environment (``CAN_INTERFACE``,
``CAN_CHANNEL``, ``CAN_BITRATE``, JSON in ``CAN_CONFIG``; with a context also the suffixed
``CAN_CHANNEL_io`` …) > config files (``~/.canrc`` …, section = context). See
:func:`can.util.load_config`. :func:`can_config_transport` uses the contexts ``fieldbus``
and ``io``, so e.g. ``CAN_INTERFACE_io=socketcan CAN_CHANNEL_io=vcan1`` configures the io
channel; the two channels must not resolve to the same bus.

Transports
    * ``hub`` (default, zero privilege): one :mod:`bus.transports.hub` server, both channels as
      logical buses on it (``<address>#fieldbus``, ``<address>#io``).
    * ``socketcan``: ``vcan0`` (fieldbus) and ``vcan1`` (io); :func:`auto_transport` picks it
      when both interfaces exist in the current network namespace.
    * ``udp_multicast``: distinct IPv4 groups and ports per channel, hop limit 1. docs/architecture.md §6
      allows it only inside a private network namespace, so :func:`open_bus` **refuses** it
      (:class:`MulticastNotAllowedError`) unless the current namespace has only loopback
      interfaces (checked with ``socket.if_nameindex()``), or the caller asserts it is in
      a private namespace with ``ChannelConfig(private_netns=True)`` or the environment
      variable ``ILCRIG_PRIVATE_NETNS=1``. On loopback a udp_multicast client receives its
      own frames (python-can does not filter them); receivers must ignore their own IDs.
      Its python-can interface is :data:`UDP_MULTICAST_INTERFACE`
      (:class:`bus.transports.udp_multicast.CheckedUdpMulticastBus`, python-can's bus with a large
      receive buffer and every datagram the kernel drops reported as a bus error frame).
    * ``virtual``: python-can's in-process bus, threads of one process only (tests).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import socket
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from bus.errors import InputError
from bus.transports.hub.addresses import default_hub_address, parse_address
from bus.transports.hub.owner import check_socket_file
from bus.transports.udp_multicast import enlarge_receive_buffer

logger = logging.getLogger(__name__)

FIELDBUS: str = "fieldbus"
IO: str = "io"
LOGICAL_CHANNELS: tuple[str, str] = (FIELDBUS, IO)

#: SocketCAN interfaces of the two channels
VCAN_FIELDBUS: str = "vcan0"
VCAN_IO: str = "vcan1"
#: udp_multicast (group, port) per channel; administratively scoped IPv4 groups
UDP_MULTICAST_GROUPS: Mapping[str, tuple[str, int]] = {
    FIELDBUS: ("239.74.163.10", 43120),
    IO: ("239.74.163.11", 43121),
}
#: set to 1/true/yes to assert "this process runs in a private network namespace"
PRIVATE_NETNS_ENV: str = "ILCRIG_PRIVATE_NETNS"

HUB_INTERFACE: str = "ilcrig_hub"
#: python-can interface name of :class:`bus.transports.udp_multicast.CheckedUdpMulticastBus` (entry
#: point); python-can's own name ``udp_multicast`` resolves to it (:func:`resolve_bus_config`)
UDP_MULTICAST_INTERFACE: str = "ilcrig_udp_multicast"


class TransportConfigError(InputError):
    """A transport or channel configuration is invalid or incomplete."""


class MulticastNotAllowedError(TransportConfigError):
    """udp_multicast outside a private network namespace (docs/architecture.md §6 forbids it)."""


@dataclass(frozen=True)
class ChannelConfig:
    """One python-can bus: ``can.Bus(interface=..., channel=..., **kwargs)``.

    :ivar interface: python-can interface name, ``None`` = from python-can's config sources
    :ivar channel: interface-specific channel, ``None`` = from python-can's config sources
    :ivar kwargs: further bus arguments (bitrate, port, receive_own_messages, …)
    :ivar context: python-can config context (config-file section, env-var suffix)
    :ivar private_netns: caller asserts the process runs in a private network namespace
        (only consulted for udp_multicast; never passed to python-can)
    """

    interface: str | None = None
    channel: str | None = None
    kwargs: Mapping[str, Any] = field(default_factory=dict)
    context: str | None = None
    private_netns: bool = False

    def as_dict(self) -> dict[str, Any]:
        """Plain dict for summary.json."""
        return {"interface": self.interface, "channel": self.channel, "kwargs": dict(self.kwargs), "context": self.context}


def net_interfaces() -> set[str]:
    """Network interface names of the *current* network namespace."""
    try:
        return {name for _, name in socket.if_nameindex()}
    except OSError:  # pragma: no cover - if_nameindex exists on Linux
        return set(os.listdir("/sys/class/net")) if os.path.isdir("/sys/class/net") else set()


def in_private_netns() -> bool:
    """True when the current network namespace has no interface but loopback."""
    names = net_interfaces()
    return bool(names) and names <= {"lo"}


def vcan_available(names: tuple[str, ...] = (VCAN_FIELDBUS, VCAN_IO)) -> bool:
    """True when all SocketCAN interfaces ``names`` exist in the current network namespace.

    Uses ``socket.if_nameindex()`` rather than ``/sys/class/net``: after ``unshare -n``
    without remounting sysfs, the latter still lists the parent namespace's interfaces.
    """
    have = net_interfaces()
    return all(n in have for n in names)


def _multicast_allowed(cfg: ChannelConfig) -> bool:
    if cfg.private_netns:
        return True
    if os.environ.get(PRIVATE_NETNS_ENV, "").strip().lower() in ("1", "true", "yes"):
        return True
    return in_private_netns()


def resolve_bus_config(cfg: ChannelConfig) -> dict[str, Any]:
    """The complete python-can bus config for ``cfg`` (precedence: see module docstring), the
    keyword arguments of ``can.Bus``. The interface ``udp_multicast`` becomes
    :data:`UDP_MULTICAST_INTERFACE`, whoever opens the bus.

    :raises TransportConfigError: no interface found anywhere, or an unknown interface
    """
    given: dict[str, Any] = dict(cfg.kwargs)
    if cfg.interface is not None:
        given["interface"] = cfg.interface
    if cfg.channel is not None:
        given["channel"] = cfg.channel
    try:
        resolved = dict(can.util.load_config(config=given, context=cfg.context))
    except can.CanInterfaceNotImplementedError as err:
        raise TransportConfigError(f"cannot resolve a CAN interface for {cfg}: {err}") from err
    if resolved["interface"] == "udp_multicast":  # python-can's bus, its losses reported as bus errors
        resolved["interface"] = UDP_MULTICAST_INTERFACE
    return resolved


#: receive buffer wanted for a SocketCAN socket, bytes: a burst (an SDO block of 127 frames, a
#: tick's frames while a reader is descheduled) must not overflow the kernel's default buffer,
#: which silently drops frames
SOCKETCAN_RCVBUF_BYTES: int = 8 << 20


def open_bus(cfg: ChannelConfig) -> can.BusABC:
    """Open the python-can bus described by ``cfg`` (``can.Bus(**resolved config)``).

    :raises MulticastNotAllowedError: udp_multicast outside a private network namespace
    :raises TransportConfigError: unresolvable configuration
    :raises can.CanInitializationError: the interface could not be opened
    """
    config = resolve_bus_config(cfg)
    if config["interface"] == UDP_MULTICAST_INTERFACE and not _multicast_allowed(cfg):
        raise MulticastNotAllowedError(
            "udp_multicast is only allowed inside a private network namespace "
            f"(this one has interfaces {sorted(net_interfaces())}); run under `unshare -rn` "
            f"or set {PRIVATE_NETNS_ENV}=1 / ChannelConfig(private_netns=True) if it is one"
        )
    logger.debug("opening bus %s", config)
    bus = can.Bus(ignore_config=True, **config)
    sock = getattr(bus, "socket", None)  # python-can's SocketcanBus keeps its socket here
    if config["interface"] == "socketcan" and sock is not None:
        enlarge_receive_buffer(sock, SOCKETCAN_RCVBUF_BYTES)
    return bus


@dataclass(frozen=True)
class TransportConfig:
    """The buses of the two logical channels.

    :ivar name: ``hub``, ``socketcan``, ``udp_multicast``, ``virtual`` or ``can_config``
    :ivar hub_address: the hub's address when ``name == "hub"`` (someone must run the hub)
    """

    name: str
    fieldbus: ChannelConfig
    io: ChannelConfig
    hub_address: str | None = None

    def channel(self, logical: str) -> ChannelConfig:
        """:raises TransportConfigError: ``logical`` is not ``fieldbus`` or ``io``"""
        if logical == FIELDBUS:
            return self.fieldbus
        if logical == IO:
            return self.io
        raise TransportConfigError(f"unknown logical channel {logical!r}; use {LOGICAL_CHANNELS}")

    def open(self, logical: str, *, passive: bool = False, can_filters: can.typechecking.CanFilters | None = None) -> can.BusABC:
        """Open the bus of logical channel ``logical``.

        :param passive: for a member that only listens and nobody waits for (a monitor, a
            logger): on the hub it joins for bulk delivery (frames held up to
            :data:`bus.transports.hub.wire.BULK_HOLD_S`, fewer writes); other transports ignore it
        :param can_filters: the member's acceptance filters (python-can's), None: every frame
        """
        cfg = self.channel(logical)
        if passive and cfg.interface == HUB_INTERFACE:
            cfg = dataclasses.replace(cfg, kwargs={**cfg.kwargs, "bulk_delivery": True})
        if can_filters is not None:
            cfg = dataclasses.replace(cfg, kwargs={**cfg.kwargs, "can_filters": can_filters})
        return open_bus(cfg)

    @property
    def needs_hub(self) -> bool:
        return self.name == "hub"

    def validate(self) -> None:
        """:raises TransportConfigError: both channels resolve to the same bus"""
        a, b = resolve_bus_config(self.fieldbus), resolve_bus_config(self.io)
        same = a["interface"] == b["interface"] and a.get("channel") == b.get("channel")
        if same and not (a["interface"] == UDP_MULTICAST_INTERFACE and a.get("port") != b.get("port")):
            raise TransportConfigError(
                f"fieldbus and io resolve to the same bus ({a['interface']} {a.get('channel')!r}); "
                "configure them separately (contexts 'fieldbus' and 'io')"
            )

    def check_usable(self, *, hub_given: bool = False) -> None:
        """Refuse, before any process starts, a transport that this machine cannot carry between
        processes (the launchers' preflight; one line naming the option and what to do).

        :param hub_given: the user gave ``--hub`` (it applies to the hub transport only)
        :raises TransportConfigError: ``virtual`` (one process only); ``socketcan`` without its
            interfaces in this network namespace; ``udp_multicast`` outside a private network
            namespace; ``--hub`` with another transport; a hub's Unix socket whose folder is missing,
            not a folder, or not this user's
        """
        if hub_given and not self.needs_hub:
            raise TransportConfigError(f"--hub applies to --bus hub (or auto without vcan) only, not to --bus {self.name}")
        if self.name == "virtual":
            raise TransportConfigError("--bus virtual: the virtual transport works inside one process only; use hub or socketcan")
        if self.name == "socketcan":
            wanted = tuple(str(c.channel) for c in (self.fieldbus, self.io))
            if not vcan_available(wanted):
                missing = ", ".join(n for n in wanted if n not in net_interfaces())
                raise TransportConfigError(
                    f"--bus socketcan: this machine has no CAN interface {missing} in this network namespace "
                    "(no vcan module in this kernel?); use --bus hub, or scripts/vcan-tests for real SocketCAN"
                )
        if self.name == "udp_multicast" and not _multicast_allowed(self.fieldbus):
            raise TransportConfigError(
                "--bus udp_multicast: only inside a private network namespace (unshare -rn); use --bus hub"
            )
        if self.needs_hub and self.hub_address is not None and hub_given:  # the default folder is made by the launcher
            addr = parse_address(self.hub_address, allow_remote=True)
            if addr.kind == "unix":
                if os.path.lexists(addr.path):
                    check_socket_file(addr.path)  # another user's socket, a link or a file: refused
                folder = Path(addr.path).absolute().parent
                if not folder.exists():
                    raise TransportConfigError(f"--hub {self.hub_address}: the folder {folder} does not exist")
                if not folder.is_dir():
                    raise TransportConfigError(f"--hub {self.hub_address}: {folder} is not a folder")
                owner = folder.stat().st_uid
                if owner != os.getuid():
                    raise TransportConfigError(
                        f"--hub {self.hub_address}: the folder {folder} is not yours (owner uid {owner}); "
                        "put the hub's socket in a folder of your own"
                    )

    def as_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "hub_address": self.hub_address,
            FIELDBUS: self.fieldbus.as_dict(),
            IO: self.io.as_dict(),
        }


def hub_transport(address: str | None = None, allow_remote: bool = False) -> TransportConfig:
    """Both channels as logical buses ``fieldbus`` / ``io`` of the hub at ``address``.

    :param address: ``unix:/path`` or ``tcp:127.0.0.1:PORT``; default
        :func:`bus.transports.hub.addresses.default_hub_address`
    :param allow_remote: a hub on another machine (non-loopback TCP address): explicit opt-in
    :raises bus.transports.hub.wire.HubAddressError: malformed or (without ``allow_remote``)
        non-loopback address
    """
    addr = address or default_hub_address()
    parse_address(addr, allow_remote)
    kwargs = {"allow_remote": True} if allow_remote else {}
    return TransportConfig(
        "hub",
        ChannelConfig(HUB_INTERFACE, f"{addr}#{FIELDBUS}", kwargs, context=FIELDBUS),
        ChannelConfig(HUB_INTERFACE, f"{addr}#{IO}", kwargs, context=IO),
        hub_address=addr,
    )


def socketcan_transport(fieldbus: str = VCAN_FIELDBUS, io: str = VCAN_IO) -> TransportConfig:
    """SocketCAN interfaces (default ``vcan0`` / ``vcan1``)."""
    return TransportConfig(
        "socketcan",
        ChannelConfig("socketcan", fieldbus, context=FIELDBUS),
        ChannelConfig("socketcan", io, context=IO),
    )


def udp_multicast_transport(private_netns: bool = False) -> TransportConfig:
    """python-can udp_multicast, distinct groups/ports per channel (see module docstring)."""

    def one(logical: str) -> ChannelConfig:
        group, port = UDP_MULTICAST_GROUPS[logical]
        return ChannelConfig(
            UDP_MULTICAST_INTERFACE, group, {"port": port, "hop_limit": 1}, context=logical, private_netns=private_netns
        )

    return TransportConfig("udp_multicast", one(FIELDBUS), one(IO))


def virtual_transport(prefix: str = "ilcrig") -> TransportConfig:
    """python-can ``virtual`` buses ``<prefix>-fieldbus`` / ``<prefix>-io`` (one process only)."""
    return TransportConfig(
        "virtual",
        ChannelConfig("virtual", f"{prefix}-{FIELDBUS}", context=FIELDBUS),
        ChannelConfig("virtual", f"{prefix}-{IO}", context=IO),
    )


def can_config_transport() -> TransportConfig:
    """Both channels entirely from python-can's config sources, contexts ``fieldbus``/``io``."""
    return TransportConfig("can_config", ChannelConfig(context=FIELDBUS), ChannelConfig(context=IO))


def auto_transport(hub_address: str | None = None, allow_remote: bool = False) -> TransportConfig:
    """SocketCAN when ``vcan0`` and ``vcan1`` both exist, else the hub at ``hub_address``."""
    if vcan_available():
        logger.info("auto transport: socketcan on %s/%s", VCAN_FIELDBUS, VCAN_IO)
        return socketcan_transport()
    cfg = hub_transport(hub_address, allow_remote)
    logger.info("auto transport: hub at %s", cfg.hub_address)
    return cfg


TRANSPORT_NAMES: tuple[str, ...] = ("auto", "hub", "socketcan", "udp_multicast", "virtual", "can_config")
#: the transports the command line offers (``virtual`` is for the threads of one process: tests)
CLI_TRANSPORT_NAMES: tuple[str, ...] = tuple(n for n in TRANSPORT_NAMES if n != "virtual")


def transport_from_name(name: str, hub_address: str | None = None, allow_remote: bool = False) -> TransportConfig:
    """Factory by name (for CLIs): one of :data:`TRANSPORT_NAMES`; ``allow_remote`` lets the hub
    transport reach a hub on another machine.

    :raises TransportConfigError: unknown name
    """
    if name == "auto":
        return auto_transport(hub_address, allow_remote)
    if name == "hub":
        return hub_transport(hub_address, allow_remote)
    if name == "socketcan":
        return socketcan_transport()
    if name == "udp_multicast":
        return udp_multicast_transport()
    if name == "virtual":
        return virtual_transport()
    if name == "can_config":
        return can_config_transport()
    raise TransportConfigError(f"--bus {name}: unknown transport; choose from {', '.join(CLI_TRANSPORT_NAMES)}")

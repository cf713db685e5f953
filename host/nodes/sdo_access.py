"""Byte-level object access to a node over the fieldbus, through the canopen library's SDO
client: the rig's implementation of the object-access protocol :class:`bus.cia301.sdo.ObjectAccess`
(``read_object(index, sub) -> bytes``, ``write_object(index, sub, data)``) that
:mod:`host.nodes.drive_client` and :mod:`host.nodes.bench_client` use.

This module owns the mapping of canopen's SDO errors to the project's: an SDO abort from the
node becomes :class:`bus.errors.SdoAbort` (same code, exactly what the in-process access
raises), a transport failure (no answer, unexpected response) :class:`SdoTransportError`.
"""

from __future__ import annotations

import logging
from typing import Any

import canopen

from bus.errors import IlcrigError, SdoAbort

logger = logging.getLogger(__name__)


class SdoTransportError(IlcrigError):
    """The node did not answer an SDO request (timeout) or answered out of protocol."""


class SdoAccess:
    """``read_object``/``write_object`` bytes of one node through ``node.sdo`` (a canopen ``RemoteNode``).

    :param node: the canopen node (anything with ``.id`` and ``.sdo.upload/.download``).
    """

    #: payloads at least this long go by SDO block transfer (half the frames of segmented)
    BLOCK_THRESHOLD: int = 64

    def __init__(self, node: Any, block_transfer: bool = True) -> None:
        self.node = node
        self.block_transfer = block_transfer

    def _is_domain(self, index: int, sub: int) -> bool:
        """True when the node's object dictionary declares ``index:sub`` a DOMAIN (tables,
        recorder data): those are read by block upload."""
        try:
            obj = self.node.object_dictionary[index]
            var = obj[sub] if hasattr(obj, "subindices") and obj.subindices else obj
            return getattr(var, "data_type", None) == 0x0F
        except (KeyError, TypeError):
            return False

    def read_block(self, index: int, sub: int) -> bytes:
        """SDO block upload (for the recorder DOMAIN)."""
        try:
            with self.node.sdo.open(index, sub, "rb", block_transfer=True) as fh:
                return bytes(fh.read())
        except canopen.SdoAbortedError as err:
            raise SdoAbort(err.code, f"node {self.node.id} read 0x{index:04X}:{sub}") from None
        except canopen.SdoCommunicationError as err:
            raise SdoTransportError(f"node {self.node.id}: read 0x{index:04X}:{sub} failed: {err}") from err

    def read_object(self, index: int, sub: int) -> bytes:
        """SDO upload of ``index:sub``.

        :raises SdoAbort: the node refused (abort code as sent).
        :raises SdoTransportError: no (valid) answer.
        """
        if self.block_transfer and self._is_domain(index, sub):
            return self.read_block(index, sub)
        try:
            return bytes(self.node.sdo.upload(index, sub))
        except canopen.SdoAbortedError as err:
            raise SdoAbort(err.code, f"node {self.node.id} read 0x{index:04X}:{sub}") from None
        except canopen.SdoCommunicationError as err:
            raise SdoTransportError(f"node {self.node.id}: read 0x{index:04X}:{sub} failed: {err}") from err

    def write_object(self, index: int, sub: int, data: bytes) -> None:
        """SDO download of ``data`` to ``index:sub`` (expedited up to 4 bytes, else segmented).

        :raises SdoAbort: the node refused (abort code as sent).
        :raises SdoTransportError: no (valid) answer.
        """
        try:
            if self.block_transfer and len(data) >= self.BLOCK_THRESHOLD:
                with self.node.sdo.open(index, sub, "wb", size=len(data), block_transfer=True) as fh:
                    fh.write(bytes(data))
            else:
                self.node.sdo.download(index, sub, bytes(data))
        except canopen.SdoAbortedError as err:
            raise SdoAbort(err.code, f"node {self.node.id} write 0x{index:04X}:{sub}") from None
        except canopen.SdoCommunicationError as err:
            raise SdoTransportError(f"node {self.node.id}: write 0x{index:04X}:{sub} failed: {err}") from err

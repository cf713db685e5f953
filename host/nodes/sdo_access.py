"""Byte-level object access to a node over the fieldbus, through the canopen library's SDO
client: the rig's implementation of the object-access protocol :class:`bus.cia301.sdo.ObjectAccess`
(``read_object(index, sub) -> bytes``, ``write_object(index, sub, data)``) that
:mod:`host.nodes.drive_client` and :mod:`host.nodes.plant_client` use.

This module owns the mapping of canopen's SDO errors to the project's: an SDO abort from the
node becomes :class:`bus.errors.SdoAbort` (same code, exactly what the in-process access
raises), a transport failure (no answer, unexpected response) :class:`SdoTransportError` — also
for requests made through canopen's own objects (``node.sdo``, ``node.rpdo``), inside
:func:`sdo_errors`.
:meth:`SdoAccess.cancel` (from another thread: the host's watchdog that declared the node or the
run lost) wakes a request waiting for its answer at once and refuses every later one, so a lost
node never holds the host for the SDO response timeout.

An interrupt (SIGINT / SIGTERM raised as :class:`KeyboardInterrupt`) inside a block transfer stays
the interrupt: canopen's stream, closed on the way out, would end the unfinished transfer and raise
its own ``SdoCommunicationError`` in place of the interrupt (a Ctrl-C would read as an
``sdo_error`` fault). The transfer is aborted at the node instead (:func:`_reraise_interrupt`).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator
from typing import Any

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoError

from bus.errors import IlcrigError, SdoAbort

logger = logging.getLogger(__name__)


__all__ = ["SdoAccess", "SdoTransportError", "sdo_errors"]


class SdoTransportError(IlcrigError):
    """The node did not answer an SDO request (timeout) or answered out of protocol, or the access
    was cancelled (:attr:`cancelled`).

    :ivar node_id: the node's id
    :ivar elapsed_s: how long the request waited before it failed, s (None: not measured)
    """

    def __init__(self, message: str, node_id: int | None = None, cancelled: bool = False, elapsed_s: float | None = None) -> None:
        super().__init__(message)
        self.node_id = node_id
        self.cancelled = cancelled
        self.elapsed_s = elapsed_s


@contextlib.contextmanager
def sdo_errors(node_id: int | None, what: str) -> Iterator[None]:
    """Inside, canopen's SDO errors (of node ``node_id``, None: any) become the project's: an
    abort :class:`bus.errors.SdoAbort`, anything else :class:`SdoTransportError` (``what``: the
    request)."""
    t0 = time.monotonic()
    who = f"node {node_id}: " if node_id is not None else ""
    try:
        yield
    except SdoAbortedError as err:
        _reraise_interrupt(err)
        raise SdoAbort(err.code, f"{who}{what}") from None
    except SdoError as err:
        _reraise_interrupt(err)
        raise SdoTransportError(f"{who}{what} failed: {err}", node_id, elapsed_s=time.monotonic() - t0) from err


def _reraise_interrupt(err: BaseException, before: Callable[[], None] | None = None) -> None:
    """Raise the :class:`KeyboardInterrupt` that ``err`` was raised while handling (its
    ``__context__`` chain: the stream's close failed because the transfer was interrupted), if
    there is one, after calling ``before``."""
    cause = err.__context__
    while cause is not None and not isinstance(cause, KeyboardInterrupt):
        cause = cause.__context__
    if cause is not None:
        if before is not None:
            before()
        raise cause


#: an SDO abort response (0x80, code 0x05040000) that :meth:`SdoAccess.cancel` puts into the
#: canopen client's response queue to wake a waiting request
_WAKE = bytes([0x80, 0, 0, 0, 0x00, 0x00, 0x04, 0x05])


class SdoAccess:
    """``read_object``/``write_object`` bytes of one node through ``node.sdo`` (a canopen ``RemoteNode``).

    :param node: the canopen node (anything with ``.id`` and ``.sdo.upload/.download``).
    """

    #: payloads at least this long go by SDO block transfer (half the frames of segmented)
    BLOCK_THRESHOLD: int = 64

    def __init__(self, node: Any, block_transfer: bool = True) -> None:
        self.node = node
        self.block_transfer = block_transfer
        self.cancelled: str | None = None

    def cancel(self, reason: str) -> None:
        """Refuse every further request (:class:`SdoTransportError` with ``reason``) and wake the
        one waiting for its response now (thread-safe).  A request made on ``node.sdo`` directly
        (canopen's own API: the bring-up's probes, the PDO configuration) fails at once too: the
        client's response timeout becomes 0 s (canopen empties the response queue when a request
        begins, so the wake reaches only a request already waiting)."""
        self.cancelled = reason
        sdo = getattr(self.node, "sdo", None)
        if sdo is not None and hasattr(sdo, "RESPONSE_TIMEOUT"):
            sdo.RESPONSE_TIMEOUT = 0.0
        responses = getattr(sdo, "responses", None)
        if responses is not None:
            responses.put(_WAKE)

    def _check(self) -> None:
        if self.cancelled is not None:
            raise SdoTransportError(f"node {self.node.id}: {self.cancelled}", self.node.id, cancelled=True)

    def _aborted(self, err: Any, what: str) -> IlcrigError:
        if self.cancelled is not None:
            return SdoTransportError(f"node {self.node.id}: {self.cancelled}", self.node.id, cancelled=True)
        return SdoAbort(err.code, f"node {self.node.id} {what}")

    def _failed(self, err: Exception, what: str, t0: float) -> SdoTransportError:
        if self.cancelled is not None:
            return SdoTransportError(f"node {self.node.id}: {self.cancelled}", self.node.id, cancelled=True)
        return SdoTransportError(f"node {self.node.id}: {what} failed: {err}", self.node.id, elapsed_s=time.monotonic() - t0)

    def _abort_quietly(self) -> None:
        """Abort the transfer in progress at the node (best effort: an interrupted block transfer
        then does not wait for its SDO timeout there)."""
        try:
            self.node.sdo.abort()
        except (can.CanError, OSError) as err:
            logger.info("node %s: the interrupted transfer could not be aborted: %s", self.node.id, err)

    def _is_domain(self, index: int, sub: int) -> bool:
        """True when the node's object dictionary declares ``index:sub`` a DOMAIN (tables,
        recorder data): those are read by block upload."""
        try:
            obj = self.node.object_dictionary[index]
            var = obj[sub] if hasattr(obj, "subindices") and obj.subindices else obj
            return getattr(var, "data_type", None) == 0x0F
        except (KeyError, TypeError):
            return False

    @contextlib.contextmanager
    def _mapped(self, what: str) -> Iterator[None]:
        """Inside, canopen's errors of the request ``what`` become the project's (module docstring);
        an interrupt that broke off a block transfer stays the interrupt."""
        t0 = time.monotonic()
        try:
            yield
        except canopen.SdoAbortedError as err:
            _reraise_interrupt(err, self._abort_quietly)
            raise self._aborted(err, what) from None
        except (SdoError, can.CanError) as err:
            _reraise_interrupt(err, self._abort_quietly)
            raise self._failed(err, what, t0) from err

    def read_block(self, index: int, sub: int) -> bytes:
        """SDO block upload (for the recorder DOMAIN)."""
        self._check()
        with self._mapped(f"read 0x{index:04X}:{sub}"), self.node.sdo.open(index, sub, "rb", block_transfer=True) as fh:
            return bytes(fh.read())

    def read_object(self, index: int, sub: int) -> bytes:
        """SDO upload of ``index:sub``.

        :raises SdoAbort: the node refused (abort code as sent).
        :raises SdoTransportError: no (valid) answer.
        """
        if self.block_transfer and self._is_domain(index, sub):
            return self.read_block(index, sub)
        self._check()
        with self._mapped(f"read 0x{index:04X}:{sub}"):
            return bytes(self.node.sdo.upload(index, sub))

    def write_object(self, index: int, sub: int, data: bytes) -> None:
        """SDO download of ``data`` to ``index:sub``: expedited up to 4 bytes, block transfer from
        :attr:`BLOCK_THRESHOLD` bytes on (when ``block_transfer``), else segmented.

        :raises SdoAbort: the node refused (abort code as sent).
        :raises SdoTransportError: no (valid) answer.
        """
        self._check()
        with self._mapped(f"write 0x{index:04X}:{sub}"):
            if self.block_transfer and len(data) >= self.BLOCK_THRESHOLD:
                with self.node.sdo.open(index, sub, "wb", size=len(data), block_transfer=True) as fh:
                    fh.write(bytes(data))
            else:
                self.node.sdo.download(index, sub, bytes(data))

"""The link to one PIL target: QEMU started as the drive's child, and the framed protocol over UART0.

Owns :class:`PilTarget`: it starts ``qemu-system-arm -M mps2-an386 -cpu cortex-m4 -icount shift=0``
on the image of :mod:`firmware_model.pil_build` with the board's UART0 on QEMU's stdio (pipes to
this process) through :func:`bus.processes.spawn_process` (the emulator dies with the drive
process), says HELLO, and exchanges one frame pair per control period.  The protocol is
documented in ``firmware_model/c/pil/pil_protocol.h``; its numbers are mirrored here
(tests/test_firmware_pil.py checks that they agree).  A QEMU that exits, faults or does not
answer within :data:`REPLY_TIMEOUT_S` (× ``ILCRIG_TIMEOUT_SCALE``) raises :class:`PilError`,
never a hang.

Also the protocol's integer coding (:func:`put_u`, :func:`put_s`, :func:`get_u`, :func:`get_s`:
LEB128 varints, zigzag for signed values).

May import: bus (and the standard library).
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import subprocess
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from bus.errors import IlcrigError
from bus.pil_fault import PilFailure
from bus.processes import spawn_process
from bus.units import timeout_scale

logger = logging.getLogger(__name__)

__all__ = ["PilError", "PilTarget", "TargetInfo", "get_s", "get_u", "put_s", "put_u", "qemu_argv", "wrap64"]

# ------------------------------------------------------------ pil_protocol.h
PROTOCOL_VERSION = 1
SYNC = 0xA5
MAX_PAYLOAD = 1024
HELLO = ord("H")
HELLO_REPLY = ord("h")
TICK = ord("T")
TICK_REPLY = ord("t")
ERROR = ord("E")
FAULT = ord("F")
#: TICK flags
TICK_COLUMN = 1
TABLE_COLS = 65537
REC_COLS = 65536
#: PIL_ERR_* codes by number
ERRORS = {
    1: "check byte mismatch",
    2: "frame too long",
    3: "unknown frame type",
    4: "malformed payload",
    5: "st slot out of range",
    6: "table column out of range",
    7: "recorder column out of range",
}

#: QEMU's instruction counting: virtual time advances 2**ICOUNT_SHIFT ns per instruction
ICOUNT_SHIFT = 0
#: the board of the target (Cortex-M4; 4 MB at 0, 4 MB RAM at 0x20000000)
MACHINE = "mps2-an386"
CPU = "cortex-m4"
#: the longest wait for a reply [s] (× ILCRIG_TIMEOUT_SCALE): shorter than the host's consumer time
#: of the drive's heartbeat (500 ms, produced every 200 ms), so a silent target is the drive's fault
#: (EMCY 0x6100), not a lost drive; the first wait (HELLO) includes QEMU's start
REPLY_TIMEOUT_S = 0.3
#: while a reply is awaited, :data:`on_wait` is called at least this often [s]
WAIT_SLICE_S = 0.05
#: called while a reply is awaited (every :data:`WAIT_SLICE_S` at least): the drive process keeps
#: its heartbeat going (:meth:`bus.cia301.slave.SlaveNode.heartbeat_if_due`), so that a target
#: that stops answering is the drive's fault after the reply time, never a drive whose last
#: heartbeat before the request plus the reply time looked like a lost node
on_wait: Callable[[], None] | None = None
BOOT_TIMEOUT_S = 20.0
_EXCEPTIONS = {2: "NMI", 3: "HardFault", 4: "MemManage", 5: "BusFault", 6: "UsageFault"}


class PilError(IlcrigError):
    """The PIL target failed: QEMU exited or did not answer in time, the core faulted, or the
    link broke the protocol.  A drive fault: the message says which target and where, and
    :attr:`failure` which of those it was (:class:`bus.pil_fault.PilFailure`, the EMCY's byte 1).
    """

    def __init__(self, message: str, failure: PilFailure = PilFailure.PROTOCOL) -> None:
        super().__init__(message)
        self.failure = failure


# ------------------------------------------------------------ integer coding


def put_u(out: bytearray, value: int) -> None:
    """Append ``value`` (>= 0) as a LEB128 varint."""
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)


def put_s(out: bytearray, value: int) -> None:
    """Append a signed ``value`` (int64 range) zigzag-coded."""
    put_u(out, (value << 1) if value >= 0 else ((-value) << 1) - 1)


def get_u(buf: bytes | bytearray, pos: int) -> tuple[int, int]:
    """(value, next position) of the varint at ``pos``.

    :raises IndexError: the buffer ends inside it"""
    b = buf[pos]
    if b < 0x80:
        return b, pos + 1
    value = b & 0x7F
    shift = 7
    pos += 1
    while True:
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if b < 0x80:
            return value, pos
        shift += 7


def wrap64(value: int) -> int:
    """``value`` modulo 2**64 as an int64 (the protocol's differences)."""
    return ((value + (1 << 63)) & ((1 << 64) - 1)) - (1 << 63)


def get_s(buf: bytes | bytearray, pos: int) -> tuple[int, int]:
    """(signed value, next position) of the zigzag varint at ``pos``."""
    u, pos = get_u(buf, pos)
    return (u >> 1) ^ -(u & 1), pos


def frame(kind: int, payload: bytes | bytearray) -> bytes:
    """One frame: SYNC, type, LEN, payload, CHECK (pil_protocol.h)."""
    head = bytearray((SYNC, kind))
    put_u(head, len(payload))
    check = (sum(head, -SYNC) + sum(payload)) & 0xFF
    return bytes(head) + bytes(payload) + bytes((check,))


# ------------------------------------------------------------ the target


@dataclass(frozen=True)
class TargetInfo:
    """What HELLO reports: protocol version, st words, table and recorder columns, SysTick clock [Hz]."""

    version: int
    n_state: int
    table_cols: int
    rec_cols: int
    systick_hz: int

    @property
    def instructions_per_tick(self) -> float:
        """Guest instructions per SysTick tick under ``-icount shift=ICOUNT_SHIFT`` (40 at 25 MHz)."""
        return 1e9 / (self.systick_hz * (1 << ICOUNT_SHIFT))


def qemu_argv(elf: Path) -> list[str]:
    """The emulator's command line: the board, UART0 on stdio, instruction counting, no display,
    monitor or default devices."""
    return [
        "qemu-system-arm",
        "-M",
        MACHINE,
        "-cpu",
        CPU,
        "-nodefaults",
        "-display",
        "none",
        "-monitor",
        "none",
        "-serial",
        "stdio",
        "-icount",
        f"shift={ICOUNT_SHIFT}",
        "-no-reboot",
        "-kernel",
        str(elf),
    ]


class PilTarget:
    """One emulated Cortex-M4 running the drive's control period (see the module docstring).

    :param elf: the image (:func:`firmware_model.pil_build.build_image`)
    :param label: who it is in messages ("node 3")
    :raises PilError: QEMU did not start or did not say HELLO
    """

    def __init__(self, elf: Path, label: str = "PIL target") -> None:
        self.label = label
        self._scale = timeout_scale()
        self._stderr: IO[bytes] = tempfile.TemporaryFile()
        self._buf = bytearray()
        self._closed = False  # close() ran: the pipes' descriptors are gone (never write to them)
        try:
            self._proc: subprocess.Popen[Any] = spawn_process(
                qemu_argv(elf), stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._stderr
            )
        except OSError as err:
            raise PilError(f"{label}: qemu-system-arm did not start: {err}") from err
        assert self._proc.stdin is not None and self._proc.stdout is not None
        self._in = self._proc.stdin.fileno()
        self._out = self._proc.stdout.fileno()
        os.set_blocking(self._out, False)
        self._poll = select.poll()
        self._poll.register(self._out, select.POLLIN)
        try:
            kind, payload = self.exchange(HELLO, b"", timeout_s=BOOT_TIMEOUT_S)
            if kind != HELLO_REPLY:
                raise PilError(f"{label}: HELLO answered with frame {chr(kind)!r}")
            values = []
            pos = 0
            for _ in range(5):
                value, pos = get_u(payload, pos)
                values.append(value)
        except BaseException:
            self.close()
            raise
        self.info = TargetInfo(*values)
        if self.info.version != PROTOCOL_VERSION:
            self.close()
            raise PilError(f"{label}: protocol version {self.info.version}, expected {PROTOCOL_VERSION}")
        logger.info("%s: QEMU pid %d up (%s)", label, self._proc.pid, self.info)

    @property
    def pid(self) -> int:
        return int(self._proc.pid)

    def exchange(self, kind: int, payload: bytes | bytearray, timeout_s: float | None = None) -> tuple[int, bytes]:
        """Send one request frame and return the reply frame (type, payload).

        :param timeout_s: the longest wait for the reply [s] (default :data:`REPLY_TIMEOUT_S`), × scale
        :raises PilError: an ERROR or FAULT frame, QEMU gone, or no reply in time
        """
        if timeout_s is None:
            timeout_s = REPLY_TIMEOUT_S
        if self._closed:
            raise PilError(f"{self.label}: the target was stopped (QEMU pid {self._proc.pid})", PilFailure.EXITED)
        try:
            os.write(self._in, frame(kind, payload))
        except (BrokenPipeError, OSError) as err:
            raise self._gone(f"could not send ({err})", PilFailure.EXITED) from None
        reply_kind, body = self._read_frame(timeout_s * self._scale)
        if reply_kind == ERROR:
            code, pos = get_u(body, 0)
            detail, _ = get_u(body, pos)
            raise PilError(f"{self.label}: the target refused a request: {ERRORS.get(code, code)} ({detail})")
        if reply_kind == FAULT:
            raise PilError(f"{self.label}: {self._fault_text(body)}", PilFailure.CORE_FAULT)
        return reply_kind, body

    def _read_frame(self, timeout_s: float) -> tuple[int, bytes]:
        buf = self._buf
        deadline = time.monotonic() + timeout_s
        while True:
            parsed = self._parse(buf)
            if parsed is not None:
                return parsed
            left = deadline - time.monotonic()
            if left <= 0:
                raise self._gone(f"no reply within {timeout_s:g} s", PilFailure.NO_ANSWER, kill=True)
            if not self._poll.poll(min(left, WAIT_SLICE_S) * 1000.0):
                if on_wait is not None:
                    on_wait()
                continue
            try:
                chunk = os.read(self._out, 65536)
            except BlockingIOError:
                continue
            if not chunk:
                raise self._gone("QEMU closed the serial line", PilFailure.EXITED)
            buf += chunk

    def _parse(self, buf: bytearray) -> tuple[int, bytes] | None:
        """A whole frame off the front of ``buf`` (bytes before SYNC dropped), or None."""
        start = buf.find(SYNC)
        if start < 0:
            buf.clear()
            return None
        if start:
            del buf[:start]
        if len(buf) < 3:
            return None
        try:
            length, pos = get_u(buf, 2)
        except IndexError:
            return None
        if length > MAX_PAYLOAD:
            raise PilError(f"{self.label}: reply frame of {length} bytes (the link lost its framing)")
        end = pos + length
        if len(buf) <= end:
            return None
        kind = buf[1]
        payload = bytes(buf[pos:end])
        if (sum(buf[1:end]) & 0xFF) != buf[end]:
            raise PilError(f"{self.label}: reply frame {chr(kind)!r} with a bad check byte")
        del buf[: end + 1]
        return kind, payload

    def _fault_text(self, body: bytes) -> str:
        exc, pos = get_u(body, 0)
        cfsr, pos = get_u(body, pos)
        hfsr, pos = get_u(body, pos)
        pc, _ = get_u(body, pos)
        name = _EXCEPTIONS.get(exc, f"exception {exc}")
        return f"the Cortex-M4 took a {name} (CFSR 0x{cfsr:08X}, HFSR 0x{hfsr:08X}) at PC 0x{pc:08X}"

    def _gone(self, what: str, failure: PilFailure, kill: bool = False) -> PilError:
        """The PilError of a broken link; stops QEMU and adds its exit status and last words."""
        if kill:
            self.close()
        rc = self._proc.poll()
        if rc is None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                rc = self._proc.wait(0.5)
        words = self._stderr_tail()
        status = "running" if rc is None else f"exit status {rc}"
        return PilError(f"{self.label}: {what} (QEMU pid {self._proc.pid}, {status}{': ' + words if words else ''})", failure)

    def _stderr_tail(self) -> str:
        try:
            self._stderr.flush()
            self._stderr.seek(0)
            text = self._stderr.read()[-400:].decode(errors="replace")
        except (OSError, ValueError):
            return ""
        return " | ".join(line.strip() for line in text.splitlines() if line.strip())

    def close(self) -> None:
        """Stop QEMU (idempotent)."""
        self._closed = True
        proc = self._proc if hasattr(self, "_proc") else None
        if proc is not None and proc.poll() is None:
            proc.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(5.0)
        if proc is not None:
            for stream in (proc.stdin, proc.stdout):
                if stream is not None:
                    with contextlib.suppress(OSError):
                        stream.close()
        with contextlib.suppress(OSError):
            self._stderr.close()

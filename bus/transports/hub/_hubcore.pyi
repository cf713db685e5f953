"""Type stub of the C extension bus/transports/hub/_hubcore.c (the hub's data plane, and a member's answer loop)."""

import threading
from collections.abc import Callable, Sequence

REPORT_EVENTS: int
REPORT_DROP: int
REPORT_REFUSE: int
BURST_TIMEOUT: int
BURST_OTHER: int
BURST_PYTHON: int
BURST_STOPPED: int
BURST_CLOSED: int
BURST_SENDFAIL: int

def answer_frames(
    fd: int,
    other_fd: int,
    deadline_s: float,
    rx_id: int,
    rx_count: int,
    rx_len: int,
    on_frame: Callable[[int, bytes], Sequence[tuple[int, bytes]] | None],
    rest: bytearray,
    lock: threading.Lock,
) -> tuple[int, int, int]: ...

class Core:
    def __init__(
        self, bits: Sequence[int], recv_chunk: int, max_outbuf: int, bulk_hold_s: float, bulk_max_bytes: int
    ) -> None: ...
    def watch(self, fd: int, events: int) -> None: ...
    def unwatch(self, fd: int) -> None: ...
    def add_member(
        self, fd: int, bus: int, echo: bool, classic: bool, bulk: bool, inbuf: bytes, outbuf: bytes, stamp_ns: int
    ) -> None: ...
    def remove(self, fd: int) -> None: ...
    def poll(self, timeout_s: float) -> list[tuple[int, int, int | str]]: ...
    def stats(self, bus: int, reset: bool = False) -> tuple[int, int, int, int, int, int]: ...
    def close(self) -> None: ...

class PeriodicWriter:
    def __init__(self, fd: int, record: bytes, period_s: float) -> None: ...
    def lease(self, seconds: float) -> None: ...
    def state(
        self, take: bool = False
    ) -> tuple[int, float | None, tuple[float, float] | None, tuple[int, float] | None, bool]: ...
    def stop(self) -> None: ...

"""Tests of bus/cia301/sdo.py: byte-exact scripted exchanges, property round trips and a conformance
test against the canopen library's SDO client over python-can's virtual bus."""

from __future__ import annotations

import itertools
import struct
import threading
import time
from collections.abc import Iterator

import can
import canopen
import pytest
from canopen import objectdictionary as od
from hypothesis import given, settings
from hypothesis import strategies as st

from bus.cia301.sdo import (
    SdoServer,
    abort_frame,
    crc16_ccitt,
    sdo_request_cob_id,
    sdo_response_cob_id,
)
from bus.errors import AbortCode, SdoAbort

NODE = 5
IDX = 0x2000  # test objects live at 0x2000:sub


class DictStore:
    """Dict-backed object store with fixed sizes, read-only and write-only objects."""

    def __init__(self) -> None:
        self.values: dict[tuple[int, int], bytes] = {
            (IDX, 1): bytes([0x11]),
            (IDX, 2): bytes([0x22, 0x33]),
            (IDX, 3): bytes([0x44, 0x55, 0x66, 0x77]),
            (IDX, 4): bytes(range(20)),  # "domain": any length
            (IDX, 5): bytes([0x01, 0x02]),  # read-only
            (IDX, 6): bytes(4),  # write-only
            (IDX, 7): b"",  # empty domain
            (0x2100, 0): bytes(range(256)) * 8,  # 2048-byte domain
        }
        self.fixed_size = {(IDX, 1): 1, (IDX, 2): 2, (IDX, 3): 4, (IDX, 5): 2, (IDX, 6): 4}
        self.read_only = {(IDX, 5)}
        self.write_only = {(IDX, 6)}
        self.writes: list[tuple[int, int, bytes]] = []

    def read_object(self, index: int, sub: int) -> bytes:
        key = (index, sub)
        if key not in self.values:
            raise SdoAbort(AbortCode.NO_OBJECT)
        if key in self.write_only:
            raise SdoAbort(AbortCode.WRITE_ONLY)
        return self.values[key]

    def write_object(self, index: int, sub: int, data: bytes) -> None:
        key = (index, sub)
        if key not in self.values:
            raise SdoAbort(AbortCode.NO_OBJECT)
        if key in self.read_only:
            raise SdoAbort(AbortCode.READ_ONLY)
        size = self.fixed_size.get(key)
        if size is not None and len(data) != size:
            raise SdoAbort(AbortCode.LENGTH_MISMATCH)
        self.values[key] = bytes(data)
        self.writes.append((index, sub, bytes(data)))


def h(text: str) -> bytes:
    return bytes.fromhex(text.replace(" ", ""))


def script(server: SdoServer, steps: list[tuple[str, str | list[str] | None]]) -> None:
    """Feed each request; assert the exact response (hex, list of hex, or None)."""
    for i, (request, expected) in enumerate(steps):
        got = server.handle(h(request))
        if expected is None:
            assert got is None, f"step {i}: expected no response, got {got!r}"
        elif isinstance(expected, list):
            assert isinstance(got, list), f"step {i}: expected a frame list, got {got!r}"
            assert [g.hex(" ") for g in got] == [h(e).hex(" ") for e in expected], f"step {i}"
        else:
            assert isinstance(got, bytes), f"step {i}: expected one frame, got {got!r}"
            assert got.hex(" ") == h(expected).hex(" "), f"step {i}"


@pytest.fixture
def store() -> DictStore:
    return DictStore()


@pytest.fixture
def server(store: DictStore) -> SdoServer:
    return SdoServer(NODE, store)


# --------------------------------------------------------------------------- COB-IDs, helpers


def test_cob_ids() -> None:
    assert sdo_request_cob_id(5) == 0x605
    assert sdo_response_cob_id(5) == 0x585
    assert sdo_response_cob_id(127) == 0x5FF
    for bad in (0, 128, -1):
        with pytest.raises(ValueError, match="1..127"):
            sdo_request_cob_id(bad)
    with pytest.raises(ValueError):
        SdoServer(0, DictStore())


def test_abort_frame_layout() -> None:
    assert abort_frame(0x6041, 0x02, 0x06020000) == h("80 41 60 02 00 00 02 06")


def test_crc_matches_ccitt_check_value() -> None:
    # CRC-16/XMODEM check value for "123456789"
    assert crc16_ccitt(b"123456789") == 0x31C3
    assert crc16_ccitt(b"") == 0


# --------------------------------------------------------------------------- expedited


def test_expedited_download_without_size_passes_four_bytes(server: SdoServer, store: DictStore) -> None:
    script(server, [("22 00 20 03 AA BB CC DD", "60 00 20 03 00 00 00 00")])
    assert store.values[(IDX, 3)] == h("AA BB CC DD")
    # a 2-byte object refuses 4 bytes
    script(server, [("22 00 20 02 AA BB 00 00", "80 00 20 02 10 00 07 06")])


# --------------------------------------------------------------------------- segmented


def test_segmented_download_20_bytes(server: SdoServer, store: DictStore) -> None:
    payload = bytes(range(0xA0, 0xA0 + 20))
    script(
        server,
        [
            ("21 00 20 04 14 00 00 00", "60 00 20 04 00 00 00 00"),
            ("00" + payload[0:7].hex(), "20 00 00 00 00 00 00 00"),
            ("10" + payload[7:14].hex(), "30 00 00 00 00 00 00 00"),
        ],
    )
    assert store.writes == [], "the object must receive the payload only at the end"
    # last segment: toggle 0, n = 1 byte unused, c = 1 -> 0x03
    script(server, [("03" + payload[14:20].hex() + "00", "20 00 00 00 00 00 00 00")])
    assert store.writes == [(IDX, 4, payload)]
    assert not server.busy


# --------------------------------------------------------------------------- aborts


@pytest.mark.parametrize("b0", ["E0", "FF", "E3"])
def test_abort_unknown_command_specifier(server: SdoServer, b0: str) -> None:
    script(server, [(b0 + " 34 12 07 00 00 00 00", "80 34 12 07 01 00 04 05")])


#: downloads that write: name → ((request, expected response) steps, the objects written with their values)
WRITES: dict[str, tuple[list[tuple[str, str | list[str] | None]], dict[tuple[int, int], bytes]]] = {
    "expedited_download_1_2_4_bytes": (
        [
            ("2F 00 20 01 AB 00 00 00", "60 00 20 01 00 00 00 00"),
            ("2B 00 20 02 CD AB 00 00", "60 00 20 02 00 00 00 00"),
            ("23 00 20 03 01 02 03 04", "60 00 20 03 00 00 00 00"),
        ],
        {(IDX, 1): h("AB"), (IDX, 2): h("CD AB"), (IDX, 3): h("01 02 03 04")},
    ),
    "segmented_download_without_size": (
        [
            ("20 00 20 04 00 00 00 00", "60 00 20 04 00 00 00 00"),
            ("00 01 02 03 04 05 06 07", "20 00 00 00 00 00 00 00"),
            ("1B 08 09 00 00 00 00 00", "30 00 00 00 00 00 00 00"),  # t=1, n=5, c=1
        ],
        {(IDX, 4): bytes(range(1, 10))},
    ),
    "block_download_without_crc": (
        [
            ("C2 00 20 03 04 00 00 00", "A0 00 20 03 7F 00 00 00"),
            ("81 01 02 03 04 00 00 00", "A2 01 7F 00 00 00 00 00"),
            ("CD 00 00 00 00 00 00 00", "A1 00 00 00 00 00 00 00"),  # n = 3
        ],
        {(IDX, 3): h("01 02 03 04")},
    ),
}


@pytest.mark.parametrize("name", WRITES)
def test_download_that_writes(server: SdoServer, store: DictStore, name: str) -> None:
    """Expedited, segmented and block downloads byte for byte: each object written once with its value."""
    steps, written = WRITES[name]
    script(server, steps)
    assert store.writes == [(index, sub, data) for (index, sub), data in written.items()] and not server.busy


#: exchanges that write nothing and leave no transfer open: name → (request, expected response) steps
WRITES_NOTHING: dict[str, list[tuple[str, str | list[str] | None]]] = {
    "segmented_upload_20_bytes": [
        ("40 00 20 04 00 00 00 00", "41 00 20 04 14 00 00 00"),
        ("60 00 00 00 00 00 00 00", "00 00 01 02 03 04 05 06"),
        ("70 00 00 00 00 00 00 00", "10 07 08 09 0A 0B 0C 0D"),
        ("60 00 00 00 00 00 00 00", "03 0E 0F 10 11 12 13 00"),
    ],
    "empty_domain_upload_is_segmented_with_size_zero": [
        ("40 00 20 07 00 00 00 00", "41 00 20 07 00 00 00 00"),
        ("60 00 00 00 00 00 00 00", "0F 00 00 00 00 00 00 00"),
    ],
    "segmented_download_size_mismatch": [
        ("21 00 20 04 08 00 00 00", "60 00 20 04 00 00 00 00"),
        ("00 01 02 03 04 05 06 07", "20 00 00 00 00 00 00 00"),
        ("13 08 09 0A 00 00 00 00", "80 00 20 04 10 00 07 06"),  # 3 bytes more than 8 - 7
    ],
    "abort_unknown_object": [
        ("40 00 30 00 00 00 00 00", "80 00 30 00 00 00 02 06"),
        ("2F 00 30 00 01 00 00 00", "80 00 30 00 00 00 02 06"),
    ],
    "abort_read_write_only": [("40 00 20 06 00 00 00 00", "80 00 20 06 01 00 01 06")],
    # 2 bytes into the 4-byte object
    "abort_wrong_length": [("2B 00 20 03 01 02 00 00", "80 00 20 03 10 00 07 06")],
    "abort_segmented_write_read_only_at_end": [
        ("21 00 20 05 02 00 00 00", "60 00 20 05 00 00 00 00"),
        ("0B 01 02 00 00 00 00 00", "80 00 20 05 02 00 01 06"),
    ],
    "abort_toggle_bit_download": [
        ("21 00 20 04 14 00 00 00", "60 00 20 04 00 00 00 00"),
        ("00 01 02 03 04 05 06 07", "20 00 00 00 00 00 00 00"),
        ("00 08 09 0A 0B 0C 0D 0E", "80 00 20 04 00 00 03 05"),  # toggle should be 1
        ("10 08 09 0A 0B 0C 0D 0E", "80 00 00 00 01 00 04 05"),  # transfer was dropped
    ],
    "abort_toggle_bit_upload": [
        ("40 00 20 04 00 00 00 00", "41 00 20 04 14 00 00 00"),
        ("70 00 00 00 00 00 00 00", "80 00 20 04 00 00 03 05"),
    ],
    "segment_request_without_transfer_is_invalid_command": [
        ("00 01 02 03 04 05 06 07", "80 00 00 00 01 00 04 05"),
        ("60 00 00 00 00 00 00 00", "80 00 00 00 01 00 04 05"),
        ("A2 01 7F 00 00 00 00 00", "80 00 00 00 01 00 04 05"),  # block ack, no block upload
        ("C1 00 00 00 00 00 00 00", "80 00 00 00 01 00 04 05"),  # block end, no download
    ],
    "wrong_segment_type_during_transfer": [
        ("40 00 20 04 00 00 00 00", "41 00 20 04 14 00 00 00"),
        ("00 01 02 03 04 05 06 07", "80 00 20 04 01 00 04 05"),  # download segment in upload
    ],
    "client_abort_drops_transfer": [
        ("21 00 20 04 14 00 00 00", "60 00 20 04 00 00 00 00"),
        ("00 01 02 03 04 05 06 07", "20 00 00 00 00 00 00 00"),
        ("80 00 20 04 00 00 04 05", None),
        ("10 01 02 03 04 05 06 07", "80 00 00 00 01 00 04 05"),
    ],
    "new_initiate_abandons_transfer": [
        ("21 00 20 04 14 00 00 00", "60 00 20 04 00 00 00 00"),
        ("00 01 02 03 04 05 06 07", "20 00 00 00 00 00 00 00"),
        ("40 00 20 01 00 00 00 00", "4F 00 20 01 11 00 00 00"),
    ],
    "expedited_upload_1_2_4_bytes": [
        ("40 00 20 01 00 00 00 00", "4F 00 20 01 11 00 00 00"),
        ("40 00 20 02 00 00 00 00", "4B 00 20 02 22 33 00 00"),
        ("40 00 20 03 00 00 00 00", "43 00 20 03 44 55 66 77"),
    ],
    "short_request_frame_is_zero_padded": [("40 00 20 01", "4F 00 20 01 11 00 00 00")],
    "abort_write_read_only": [("2B 00 20 05 FF FF 00 00", "80 00 20 05 02 00 01 06")],
    "block_download_crc_error": [
        ("C6 00 20 03 04 00 00 00", "A4 00 20 03 7F 00 00 00"),
        ("81 01 02 03 04 00 00 00", "A2 01 7F 00 00 00 00 00"),
        ("CD 12 34 00 00 00 00 00", "80 00 20 03 04 00 04 05"),
    ],
    "block_download_size_mismatch": [
        ("C2 00 20 04 05 00 00 00", "A0 00 20 04 7F 00 00 00"),
        ("81 01 02 03 04 00 00 00", "A2 01 7F 00 00 00 00 00"),
        ("CD 00 00 00 00 00 00 00", "80 00 20 04 10 00 07 06"),
    ],
    "block_download_client_abort_in_subblock": [
        ("C2 00 20 04 14 00 00 00", "A0 00 20 04 7F 00 00 00"),
        ("01 00 01 02 03 04 05 06", None),
        ("80 00 20 04 00 00 00 08", None),
    ],
    "block_upload_without_crc_small_blocks_and_repeat": [
        ("A0 00 20 04 02 00 00 00", "C2 00 20 04 14 00 00 00"),
        ("A3 00 00 00 00 00 00 00", ["01 00 01 02 03 04 05 06", "02 07 08 09 0A 0B 0C 0D"]),
        # the client only got the first segment: the server repeats from the second
        ("A2 01 02 00 00 00 00 00", ["01 07 08 09 0A 0B 0C 0D", "82 0E 0F 10 11 12 13 00"]),
        ("A2 02 02 00 00 00 00 00", "C5 00 00 00 00 00 00 00"),
        ("A1 00 00 00 00 00 00 00", None),
    ],
}


@pytest.mark.parametrize("name", WRITES_NOTHING)
def test_exchange_that_writes_nothing(server: SdoServer, store: DictStore, name: str) -> None:
    """Uploads, refused and aborted transfers byte for byte: nothing written, no transfer left open."""
    script(server, WRITES_NOTHING[name])
    assert store.writes == [] and not server.busy


def test_timeout_aborts_abandoned_transfer(server: SdoServer, store: DictStore) -> None:
    assert server.tick(10.0) is None  # idle: nothing to time out
    script(server, [("21 00 20 04 14 00 00 00", "60 00 20 04 00 00 00 00")])
    assert server.busy
    assert server.tick(10.5) is None
    assert server.handle(h("00 01 02 03 04 05 06 07"), now_s=10.9) == h("20" + "00" * 7)
    assert server.tick(11.8) is None  # 0.9 s since the last frame
    frame = server.tick(12.0)
    assert frame == h("80 00 20 04 00 00 04 05")
    assert not server.busy and store.writes == []
    assert server.tick(20.0) is None
    script(server, [("10 01 02 03 04 05 06 07", "80 00 00 00 01 00 04 05")])


def test_timeout_without_prior_time(store: DictStore) -> None:
    server = SdoServer(NODE, store)
    server.TIMEOUT_S = 0.1
    script(server, [("40 00 20 04 00 00 00 00", "41 00 20 04 14 00 00 00")])
    assert server.tick(100.0) is None  # first time reference
    assert server.tick(100.2) == h("80 00 20 04 00 00 04 05")


# --------------------------------------------------------------------------- block download


def test_block_download_with_crc(server: SdoServer, store: DictStore) -> None:
    payload = bytes(range(0xA0, 0xA0 + 20))
    crc = crc16_ccitt(payload)
    script(
        server,
        [
            ("C6 00 20 04 14 00 00 00", "A4 00 20 04 7F 00 00 00"),
            ("01" + payload[0:7].hex(), None),
            ("02" + payload[7:14].hex(), None),
            ("83" + payload[14:20].hex() + "00", "A2 03 7F 00 00 00 00 00"),
        ],
    )
    assert store.writes == []
    # end: n = 1 unused byte in the last segment -> 0xC1 | 1 << 2 = 0xC5, CRC LE
    script(server, [(f"C5 {crc & 0xFF:02X} {crc >> 8:02X} 00 00 00 00 00", "A1 00 00 00 00 00 00 00")])
    assert store.writes == [(IDX, 4, payload)]
    assert not server.busy


def test_block_download_multiple_subblocks_and_lost_segment(store: DictStore) -> None:
    server = SdoServer(NODE, store)
    server.BLOCK_SIZE = 2
    payload = bytes(range(30))  # 5 segments
    seg = [payload[i : i + 7].ljust(7, b"\x00").hex() for i in range(0, 30, 7)]
    script(
        server,
        [
            ("C2 00 20 04 1E 00 00 00", "A0 00 20 04 02 00 00 00"),
            ("01" + seg[0], None),
            ("02" + seg[1], "A2 02 02 00 00 00 00 00"),
            # segment 1 of the second sub-block is lost: seqno 2 arrives first
            ("02" + seg[3], "A2 00 02 00 00 00 00 00"),
            # the client repeats the whole sub-block
            ("01" + seg[2], None),
            ("02" + seg[3], "A2 02 02 00 00 00 00 00"),
            ("81" + seg[4], "A2 01 02 00 00 00 00 00"),
            ("D5 00 00 00 00 00 00 00", "A1 00 00 00 00 00 00 00"),  # n = 5 -> 0xC1 | 0x14
        ],
    )
    assert store.values[(IDX, 4)] == payload


def test_block_download_segments_look_like_other_commands(server: SdoServer, store: DictStore) -> None:
    """In the sub-block phase, 0x21, 0x40, 0x60 ... are sequence numbers, not commands."""
    payload = bytes(i & 0xFF for i in range(7 * 0x61))
    frames = [("C0 00 20 04 00 00 00 00", "A0 00 20 04 7F 00 00 00")]
    for k in range(0x61):
        seqno = k + 1
        flag = 0x80 if seqno == 0x61 else 0
        frames.append((f"{flag | seqno:02X}" + payload[7 * k : 7 * k + 7].hex(), "A2 61 7F 00 00 00 00 00" if flag else None))
    frames.append(("C1 00 00 00 00 00 00 00", "A1 00 00 00 00 00 00 00"))
    script(server, frames)
    assert store.values[(IDX, 4)] == payload


# --------------------------------------------------------------------------- block upload


def test_block_upload_with_crc(server: SdoServer) -> None:
    payload = bytes(range(20))
    crc = crc16_ccitt(payload)
    script(
        server,
        [
            ("A4 00 20 04 7F 00 00 00", "C6 00 20 04 14 00 00 00"),
            (
                "A3 00 00 00 00 00 00 00",
                [
                    "01 00 01 02 03 04 05 06",
                    "02 07 08 09 0A 0B 0C 0D",
                    "83 0E 0F 10 11 12 13 00",
                ],
            ),
            ("A2 03 7F 00 00 00 00 00", f"C5 {crc & 0xFF:02X} {crc >> 8:02X} 00 00 00 00 00"),
            ("A1 00 00 00 00 00 00 00", None),
        ],
    )
    assert not server.busy


def test_block_upload_protocol_switch(server: SdoServer) -> None:
    script(server, [("A4 00 20 03 7F 04 00 00", "43 00 20 03 44 55 66 77")])
    script(
        server,
        [
            ("A4 00 20 04 7F 20 00 00", "41 00 20 04 14 00 00 00"),
            ("60 00 00 00 00 00 00 00", "00 00 01 02 03 04 05 06"),
        ],
    )


def test_block_upload_aborts(server: SdoServer) -> None:
    script(
        server,
        [
            ("A4 00 20 04 00 00 00 00", "80 00 20 04 02 00 04 05"),  # block size 0
            ("A4 00 20 04 80 00 00 00", "80 00 20 04 02 00 04 05"),  # block size 128
            ("A4 00 30 00 7F 00 00 00", "80 00 30 00 00 00 02 06"),  # unknown object
            ("A4 00 20 04 02 00 00 00", "C6 00 20 04 14 00 00 00"),
            ("A2 00 02 00 00 00 00 00", "80 00 20 04 01 00 04 05"),  # ack before start
        ],
    )
    script(
        server,
        [
            ("A4 00 20 04 02 00 00 00", "C6 00 20 04 14 00 00 00"),
            ("A3 00 00 00 00 00 00 00", ["01 00 01 02 03 04 05 06", "02 07 08 09 0A 0B 0C 0D"]),
            ("A2 03 02 00 00 00 00 00", "80 00 20 04 03 00 04 05"),  # acks more than sent
        ],
    )


# --------------------------------------------------------------------------- property tests


def _segmented_download(server: SdoServer, index: int, sub: int, data: bytes) -> None:
    resp = server.handle(struct.pack("<BHBL", 0x21, index, sub, len(data)))
    assert resp == struct.pack("<BHB", 0x60, index, sub) + bytes(4)
    toggle = 0
    chunks = [data[i : i + 7] for i in range(0, len(data), 7)] or [b""]
    for k, chunk in enumerate(chunks):
        last = k == len(chunks) - 1
        b0 = (toggle << 4) | ((7 - len(chunk)) << 1) | int(last)
        resp = server.handle(bytes([b0]) + chunk.ljust(7, b"\x00"))
        assert resp == bytes([0x20 | (toggle << 4)]) + bytes(7)
        toggle ^= 1


def _segmented_upload(server: SdoServer, index: int, sub: int) -> bytes:
    resp = server.handle(struct.pack("<BHBL", 0x40, index, sub, 0))
    assert isinstance(resp, bytes)
    if resp[0] & 0x02:
        return resp[4 : 8 - ((resp[0] >> 2) & 3)]
    assert resp[0] == 0x41
    size = struct.unpack_from("<L", resp, 4)[0]
    out = bytearray()
    toggle = 0
    while True:
        seg = server.handle(bytes([0x60 | (toggle << 4)]) + bytes(7))
        assert isinstance(seg, bytes) and (seg[0] >> 4) & 1 == toggle
        out += seg[1 : 8 - ((seg[0] >> 1) & 7)]
        toggle ^= 1
        if seg[0] & 1:
            break
    assert len(out) == size
    return bytes(out)


def _block_upload(server: SdoServer, index: int, sub: int, blksize: int) -> bytes:
    resp = server.handle(struct.pack("<BHBBBH", 0xA4, index, sub, blksize, 0, 0))
    assert isinstance(resp, bytes) and resp[0] == 0xC6
    size = struct.unpack_from("<L", resp, 4)[0]
    frames = server.handle(bytes([0xA3]) + bytes(7))
    data = bytearray()
    while True:
        assert isinstance(frames, list) and 1 <= len(frames) <= blksize
        for k, f in enumerate(frames):
            assert f[0] & 0x7F == k + 1
            data += f[1:]
        resp = server.handle(bytes([0xA2, len(frames), blksize]) + bytes(5))
        if isinstance(resp, bytes):
            break
        frames = resp
    n = (resp[0] >> 2) & 7
    assert resp[0] & 0xE3 == 0xC1
    out = bytes(data[: len(data) - n])
    assert struct.unpack_from("<H", resp, 1)[0] == crc16_ccitt(out)
    assert server.handle(bytes([0xA1]) + bytes(7)) is None
    assert len(out) == size
    return out


def _block_download(server: SdoServer, index: int, sub: int, data: bytes) -> None:
    resp = server.handle(struct.pack("<BHBL", 0xC6, index, sub, len(data)))
    assert isinstance(resp, bytes) and resp[0] == 0xA4
    blksize = resp[4]
    chunks = [data[i : i + 7] for i in range(0, len(data), 7)] or [b""]
    seqno = 0
    for k, chunk in enumerate(chunks):
        last = k == len(chunks) - 1
        seqno += 1
        resp = server.handle(bytes([seqno | (0x80 if last else 0)]) + chunk.ljust(7, b"\x00"))
        if last or seqno == blksize:
            assert resp == bytes([0xA2, seqno, blksize]) + bytes(5)
            seqno = 0
        else:
            assert resp is None
    n = 7 - len(chunks[-1])
    crc = crc16_ccitt(data)
    assert server.handle(struct.pack("<BH", 0xC1 | (n << 2), crc) + bytes(5)) == (bytes([0xA1]) + bytes(7))


@settings(max_examples=60, deadline=None)
@given(payload=st.binary(min_size=0, max_size=300))
def test_segmented_round_trip(payload: bytes) -> None:
    store = DictStore()
    server = SdoServer(NODE, store)
    _segmented_download(server, IDX, 4, payload)
    assert store.values[(IDX, 4)] == payload
    assert _segmented_upload(server, IDX, 4) == payload
    assert not server.busy


@settings(max_examples=60, deadline=None)
@given(payload=st.binary(min_size=0, max_size=300), blksize=st.integers(min_value=1, max_value=127))
def test_block_round_trip(payload: bytes, blksize: int) -> None:
    store = DictStore()
    server = SdoServer(NODE, store)
    server.BLOCK_SIZE = blksize
    _block_download(server, IDX, 4, payload)
    assert store.values[(IDX, 4)] == payload
    assert _block_upload(server, IDX, 4, blksize) == payload
    assert not server.busy


@settings(max_examples=100, deadline=None)
@given(frames=st.lists(st.binary(min_size=0, max_size=8), max_size=30))
def test_random_frames_never_raise(frames: list[bytes]) -> None:
    """Garbage in: the server answers with frames or nothing, never an exception."""
    server = SdoServer(NODE, DictStore())
    for t, f in enumerate(frames):
        resp = server.handle(f, now_s=float(t))
        assert resp is None or isinstance(resp, (bytes, list))
        if isinstance(resp, bytes):
            assert len(resp) == 8
        server.tick(float(t) + 0.5)


# --------------------------------------------------------------------------- conformance


_channel_counter = itertools.count()


class ServerThread:
    """Answers SDO requests on its own virtual bus with SdoServer.handle; counts frames."""

    def __init__(self, channel: str, server: SdoServer) -> None:
        self.server = server
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.stop = threading.Event()
        self.requests = 0
        self.responses = 0
        self.thread = threading.Thread(target=self._run, name="sdo-server", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            msg = self.bus.recv(timeout=0.02)
            if msg is None:
                continue
            if msg.arbitration_id != self.server.request_cob_id:
                continue
            self.requests += 1
            resp = self.server.handle(bytes(msg.data), now_s=time.monotonic())
            frames = [] if resp is None else [resp] if isinstance(resp, bytes) else resp
            for data in frames:
                self.bus.send(can.Message(arbitration_id=self.server.response_cob_id, data=data, is_extended_id=False))
                self.responses += 1

    def reset_counts(self) -> None:
        self.requests = self.responses = 0

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=2.0)
        self.bus.shutdown()


def _make_od() -> od.ObjectDictionary:
    dictionary = od.ObjectDictionary()
    for sub, name, dtype in (
        (1, "u8", od.UNSIGNED8),
        (2, "i16", od.INTEGER16),
        (3, "u32", od.UNSIGNED32),
        (4, "domain", od.DOMAIN),
        (5, "ro", od.UNSIGNED16),
    ):
        # one variable per index keeps canopen's SDO mapping simple
        var = od.ODVariable(name, IDX + sub * 0x10, 0)
        var.data_type = dtype
        var.access_type = "ro" if name == "ro" else "rw"
        dictionary.add_object(var)
    big = od.ODVariable("table", 0x2100, 0)
    big.data_type = od.DOMAIN
    dictionary.add_object(big)
    return dictionary


class FlatStore(DictStore):
    """DictStore re-keyed to the conformance OD's one-variable-per-index layout."""

    def __init__(self) -> None:
        super().__init__()
        remap = {(IDX, s): (IDX + s * 0x10, 0) for s in range(1, 8)}
        self.values = {remap.get(k, k): v for k, v in self.values.items()}
        self.fixed_size = {remap[k]: v for k, v in self.fixed_size.items()}
        self.read_only = {remap[k] for k in self.read_only}
        self.write_only = {remap[k] for k in self.write_only}


@pytest.fixture
def conformance() -> Iterator[tuple[canopen.RemoteNode, ServerThread, FlatStore]]:
    channel = f"ilcrig-sdo-{next(_channel_counter)}"
    store = FlatStore()
    server = ServerThread(channel, SdoServer(NODE, store))
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.02  # quick teardown: the notifier thread polls at this period
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    node = canopen.RemoteNode(NODE, _make_od())
    network.add_node(node)
    try:
        yield node, server, store
    finally:
        network.disconnect()
        server.close()


@pytest.fixture(autouse=True)
def _no_leaked_virtual_channels() -> Iterator[None]:
    from can.interfaces import virtual

    yield
    assert not virtual.channels, f"virtual channels left open: {list(virtual.channels)}"


def test_conformance_expedited(conformance) -> None:
    node, server, store = conformance
    node.sdo[0x2010].raw = 0xAB
    node.sdo[0x2020].raw = -2
    node.sdo[0x2030].raw = 0xDEADBEEF
    assert store.values[(0x2010, 0)] == h("AB")
    assert store.values[(0x2020, 0)] == h("FE FF")
    assert store.values[(0x2030, 0)] == h("EF BE AD DE")
    assert node.sdo[0x2010].raw == 0xAB
    assert node.sdo[0x2020].raw == -2
    assert node.sdo[0x2030].raw == 0xDEADBEEF
    assert node.sdo[0x2050].raw == 0x0201
    assert server.requests == 7 and server.responses == 7


def test_conformance_segmented_domain(conformance) -> None:
    node, server, store = conformance
    payload = bytes((i * 7 + 3) & 0xFF for i in range(2000))
    node.sdo.download(0x2100, 0, payload)
    assert store.values[(0x2100, 0)] == payload
    assert server.requests == 1 + 286 and server.responses == 1 + 286  # ceil(2000/7) = 286
    server.reset_counts()
    assert node.sdo.upload(0x2100, 0) == payload
    assert server.requests == 287 and server.responses == 287
    # small domain and a forced segmented int
    node.sdo.download(0x2040, 0, b"abc", force_segment=True)
    assert node.sdo.upload(0x2040, 0) == b"abc"
    node.sdo.download(0x2030, 0, struct.pack("<L", 7), force_segment=True)
    assert node.sdo[0x2030].raw == 7


@pytest.mark.parametrize("crc", [True, False])
def test_conformance_block_transfer(conformance, crc: bool) -> None:
    node, server, store = conformance
    payload = bytes((i * 13 + 1) & 0xFF for i in range(2000))
    with node.sdo.open(0x2100, 0, "wb", size=len(payload), block_transfer=True, request_crc_support=crc) as fp:
        fp.write(payload)
    assert store.values[(0x2100, 0)] == payload
    block_down = server.requests + server.responses
    # initiate 2 + 286 segments + 3 acks + end 2 = 293 frames (the segmented one takes 574)
    assert block_down == 293
    server.reset_counts()
    with node.sdo.open(0x2100, 0, "rb", block_transfer=True, request_crc_support=crc) as fp:
        assert fp.read() == payload
    # wait for the client's closing end frame to be consumed by the server
    deadline = time.monotonic() + 1.0
    while server.server.busy and time.monotonic() < deadline:
        time.sleep(0.005)
    assert not server.server.busy
    assert server.requests + server.responses == 294  # 2 + start + 286 + 3 acks + end + end


def test_conformance_abort_codes(conformance) -> None:
    node, _, _ = conformance
    cases = [
        (lambda: node.sdo.upload(0x3000, 0), 0x06020000),
        (lambda: node.sdo.download(0x2050, 0, b"\x01\x00"), 0x06010002),
        (lambda: node.sdo.download(0x2030, 0, b"\x01\x00"), 0x06070010),
        (lambda: node.sdo.download(0x2050, 0, bytes(40)), 0x06010002),  # segmented, at end
        (lambda: node.sdo.upload(0x2060, 0), 0x06010001),
    ]
    for call, code in cases:
        with pytest.raises(canopen.SdoAbortedError) as err:
            call()
        assert err.value.code == code
    # block transfer aborts as well
    with pytest.raises(canopen.SdoAbortedError) as err:
        with node.sdo.open(0x3000, 0, "rb", block_transfer=True) as fp:
            fp.read()
    assert err.value.code == 0x06020000
    # the server is still usable afterwards
    assert node.sdo[0x2010].raw == 0x11

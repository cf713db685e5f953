"""Test helpers for the CiA 402 drive tests: a stand-in plant whose position follows the drive's
demand exactly, object access by format, a reference transcription of the profile rules, and a
drive node served in a thread as the canopen library sees it (:func:`canopen_view`), and the first
answer of a drive process that is starting (:func:`vendor_id_once_up`).

The echo plant: with Kp = ``K`` µN·m per count (Q16: ``K << 16``), Kd = 0 and no feed-forward the
drive's torque is exactly ``K · (demand − count)``; the plant integrates it as a velocity source,
``count[n+1] = count[n] + τ[n] // K``, so the encoder count of tick n+1 is the position demand of
tick n, to the count.  Positions after a move can therefore be predicted exactly from the integer
profile (:func:`reference_profile`, a transcription of the rules in firmware_model/profile.py's
docstring, written apart from the firmware).
"""

from __future__ import annotations

import contextlib
import struct
import subprocess
import threading
import time
from collections.abc import Iterator
from math import isqrt
from typing import Any

import canopen
from clock_util import SDO_RESPONSE_S

from bus import fixedpoint as fp
from bus.cia301.nmt import NmtCommand
from bus.objects import DRIVE_EDS_PATH, GainsSub, Obj
from firmware_model.drive import Drive
from firmware_model.drive_node import DriveNode

#: µN·m per count of the echo plant (= the drive's Kp)
K_ECHO = 1000
_FMT = {"u8": "<B", "i8": "<b", "u16": "<H", "i16": "<h", "u32": "<I", "i32": "<i"}


def wr(d: Drive, index: int, sub: int, fmt: str, value: int) -> None:
    d.write_object(index, sub, struct.pack(_FMT[fmt], value))


def rd(d: Drive, index: int, sub: int, fmt: str) -> int:
    return int(struct.unpack(_FMT[fmt], d.read_object(index, sub))[0])


class EchoPlant:
    """The stand-in plant (see the module docstring) of one drive."""

    def __init__(self, count: int = 0) -> None:
        self.count = count
        self.tick = 0

    def step(self, d: Drive) -> int:
        """One io tick of ``d``: returns the torque; the encoder count moves by τ // K."""
        tau = d.io_tick(self.tick, self.count)
        d.service()
        self.tick += 1
        self.count += tau // K_ECHO
        return tau

    def run(self, d: Drive, n: int) -> list[int]:
        """``n`` ticks: the encoder count after each."""
        out = []
        for _ in range(n):
            self.step(d)
            out.append(self.count)
        return out


def echo_drive(node_id: int = 2, mode: int = 1, start: int = 0, enable: bool = True) -> tuple[Drive, EchoPlant]:
    """A drive with the echo plant's gains, NMT OPERATIONAL, in ``mode``, one tick at ``start``
    counts (the position actual), then enabled (Operation enabled)."""
    d = Drive(node_id)
    wr(d, Obj.GAINS, GainsSub.KP, "i32", K_ECHO << fp.KP_Q)
    wr(d, Obj.GAINS, GainsSub.KD, "i32", 0)
    d.nmt_command(NmtCommand.START)
    wr(d, Obj.MODES_OF_OPERATION, 0, "i8", mode)
    plant = EchoPlant(start)
    plant.step(d)  # torque off: the drive reads its encoder
    if enable:
        for cw in (0x06, 0x07, 0x0F):
            wr(d, Obj.CONTROLWORD, 0, "u16", cw)
    return d, plant


def reference_profile(start: int, target: int, v_max: int, acc: int, dec: int) -> list[int]:
    """The demand positions [counts] of a profile-position move from rest at ``start`` to ``target``
    [counts] with per-cycle Q16 rates, one entry per control cycle, the last on the target."""
    p, v, out = start << 16, 0, []
    goal = target << 16
    while True:
        d = goal - p
        s = 1 if d > 0 else -1
        u = v * s
        if u < 0:
            u_new = min(u + dec, 0)
        else:
            u_new = max(min(u + acc, v_max, (isqrt(8 * dec * abs(d) + dec * dec) - dec) // 2), u - dec)
            if abs(d) <= u_new:
                out.append(target)
                return out
        v = s * u_new
        p += v
        out.append(fp.profile_position_counts(p))


@contextlib.contextmanager
def canopen_view(node: DriveNode, node_id: int, **connect: Any) -> Iterator[tuple[canopen.Network, canopen.RemoteNode]]:
    """``node`` served in a thread, and the canopen library's view of it: a network connected with
    ``connect`` (python-can's bus arguments), the drive added from its EDS with a 5 s SDO timeout.
    On the way out the network is disconnected and the node's thread stopped (the buses are the
    caller's)."""
    stop = threading.Event()
    thread = threading.Thread(target=node.run, args=(stop,), daemon=True)
    thread.start()
    network = canopen.Network()
    network.connect(**connect)
    try:
        remote = network.add_node(node_id, str(DRIVE_EDS_PATH))
        remote.sdo.RESPONSE_TIMEOUT = SDO_RESPONSE_S
        yield network, remote
    finally:
        network.disconnect()
        stop.set()
        thread.join(5)
    assert not thread.is_alive()


def vendor_id_once_up(node: canopen.RemoteNode, proc: subprocess.Popen[Any], wait_s: float) -> int:
    """The vendor-ID (0x1018:1) of the drive process ``proc`` that is starting, asked by SDO again
    until it answers.

    :raises canopen.SdoCommunicationError: no answer within ``wait_s``, or the process ended
    """
    deadline = time.monotonic() + wait_s
    while True:
        try:
            return int(node.sdo[0x1018][1].raw)
        except canopen.SdoCommunicationError:
            if time.monotonic() > deadline or proc.poll() is not None:
                raise

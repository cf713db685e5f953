"""The end of a rig trial: the channel monitors' explicit end-of-trial markers (host.rig.channels,
host.rig.monitor, bus.io_frames.TrialTickFollower.ended) and the host's trial boundary figures
(host.rig.realtime.host_timing)."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator

import can
import pytest

from bus.io_frames import IoControlCommand, TorqueStatus, TrialTickFollower, encode_control, encode_encoder, encode_torque
from bus.plant_objects import TrialTiming
from bus.transports.config import FIELDBUS, IO, TransportConfig, virtual_transport
from host.rig.bus_accounting import BusTimeAccounting
from host.rig.channels import RigChannels
from host.rig.realtime import HostBoundary, timing_summary

_prefix = itertools.count()


def test_the_follower_marks_the_trial_whose_stop_it_saw() -> None:
    f = TrialTickFollower()
    assert f.ended == -1
    for k in range(3):
        f.on_frame(0x010, bytes(encode_control(IoControlCommand.TRIAL_START, 100 * k, 5).data))
        assert (f.trial, f.ended, f.in_trial) == (k, k - 1, True)
        f.on_frame(0x010, bytes(encode_control(IoControlCommand.TRIAL_STOP, 100 * k + 5, 5).data))
        assert (f.trial, f.ended, f.in_trial) == (k, k, False)


@pytest.fixture
def channels() -> Iterator[tuple[RigChannels, TransportConfig]]:
    tc = virtual_transport(prefix=f"boundary-test-{next(_prefix)}")
    bus_time = BusTimeAccounting(ts_s=0.001, trial_s=0.3, heartbeat_ms=200, n_nodes=6)
    rc = RigChannels(tc, None, bus_time)
    try:
        yield rc, tc
    finally:
        rc.close()


def _trial(io: can.BusABC, ticks: int, stop: bool = True) -> None:
    io.send(encode_control(IoControlCommand.TRIAL_START, 0, ticks))
    for n in range(ticks):
        for j in range(4):
            io.send(encode_encoder(j, n, j))
        for j in range(4):
            io.send(encode_torque(j, n, 0, TorqueStatus.ENABLED))
    if stop:
        io.send(encode_control(IoControlCommand.TRIAL_STOP, ticks, ticks))


def test_the_end_of_a_trial_is_awaited_by_its_markers(channels: tuple[RigChannels, TransportConfig]) -> None:
    rc, tc = channels
    io, fieldbus = tc.open(IO), tc.open(FIELDBUS)
    try:
        for k in range(2):
            io_trial = rc.next_trial()
            assert io_trial == k
            _trial(io, 50)
            end = time.time()
            fieldbus.send(can.Message(arbitration_id=0x5A0, data=b"\x60\x40\x24\x00\x00\x00\x00\x00", is_extended_id=False))
            assert rc.wait_trial_end(io_trial, end, timeout_s=10.0)
            io_mon = rc.io
            assert io_mon is not None and io_mon.follower.ended == k
            # every io frame of the trial was counted before the trial is kept
            assert io_mon.counter.as_dict()["frames"] == (k + 1) * (50 * 8 + 2)
    finally:
        io.shutdown()
        fieldbus.shutdown()


def test_a_marker_that_never_comes_ends_the_wait_at_its_timeout(channels: tuple[RigChannels, TransportConfig]) -> None:
    rc, tc = channels
    io = tc.open(IO)
    try:
        io_trial = rc.next_trial()
        _trial(io, 3, stop=False)  # no TRIAL_STOP, and nothing on the fieldbus after the end
        t0 = time.monotonic()
        assert not rc.wait_trial_end(io_trial, time.time(), timeout_s=0.3)
        assert 0.25 <= time.monotonic() - t0 < 5.0
    finally:
        io.shutdown()


def test_the_host_boundary_is_summarised_beside_the_plant_rate() -> None:
    timings = [TrialTiming(False, 500, 250_000, 0, 0, 0, 0)] * 2
    bounds = [HostBoundary(0.002, 0.255, 0.003)] * 2
    s = timing_summary(timings, 0.001, False, host=bounds)
    host = s["host"]
    assert host["seconds"] == pytest.approx(0.52)
    assert (host["setup_s"], host["ticks_s"], host["end_s"]) == pytest.approx((0.004, 0.51, 0.006))
    assert host["ticks_per_s"] == pytest.approx(1000 / 0.52)
    assert host["of_plant_rate"] == pytest.approx((1000 / 0.52) / 2000)
    assert len(host["per_trial"]) == 2
    assert "host" not in timing_summary(timings, 0.001, False)

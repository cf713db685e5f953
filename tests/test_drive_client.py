"""DriveClient driving an in-process Drive (the Drive itself is the object access) through a short trial against a
toy float double-integrator plant written here."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from bus import fixedpoint as fp
from bus.objects import FaultCause, Obj, RecorderStatus, TrialState
from bus.units import RAD_PER_COUNT, TORQUE_LSB_NM, rad_to_counts
from firmware_model.cia402 import Cia402State
from firmware_model.drive import Drive
from host.nodes.drive_client import DriveClient, DriveInputError, DriveStateError

TS = 1e-3
J = 0.1  # kg·m², toy joint inertia


class DoubleIntegrator:
    """J q̈ = τ with τ held over each tick (exact ZOH integration)."""

    def __init__(self, q0: float, qd0: float) -> None:
        self.q, self.qd = q0, qd0

    def counts(self) -> int:
        return rad_to_counts(self.q)

    def step(self, tau_units: int) -> None:
        acc = tau_units * TORQUE_LSB_NM / J
        self.q += self.qd * TS + 0.5 * acc * TS * TS
        self.qd += acc * TS


def reference(n: int, amp: float = 0.2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cosine move 0 -> amp over the trial: q, q̇, q̈."""
    t = np.arange(n) * TS
    T = (n - 1) * TS
    w = math.pi / T
    q = amp * 0.5 * (1 - np.cos(w * t))
    qd = amp * 0.5 * w * np.sin(w * t)
    qdd = amp * 0.5 * w * w * np.cos(w * t)
    return q, qd, qdd


def make(node: int = 2) -> tuple[Drive, DriveClient]:
    drive = Drive(node)
    drive.nmt_command(0x01)
    client = DriveClient(drive, node)
    client.set_mode(-1)  # table playback (the drive boots in profile position)
    return drive, client


def run(drive: Drive, plant: DoubleIntegrator, n_ticks: int) -> list[int]:
    taus = []
    for n in range(n_ticks):
        tau = drive.io_tick(n, plant.counts())
        taus.append(tau)
        plant.step(tau)
    return taus


def test_short_trial_against_toy_plant() -> None:
    n = 301
    q, qd, qdd = reference(n)
    drive, client = make()
    client.configure(300.0, 10.0, vel_filter=0.5, torque_limit_nm=50.0, following_error_rad=0.05)
    kp, kd, a = client.gains()
    assert abs(kp - 300.0) <= 0.5 * fp.KP_LSB_NM_PER_RAD
    assert abs(kd - 10.0) <= 0.5 * fp.KD_LSB_NMS_PER_RAD
    assert a == 0.5
    client.configure(300.0, 10.0)  # unfiltered velocity (default) for the trial below
    assert drive.read_object(Obj.MAX_TORQUE, 0) == struct.pack("<H", round(50.0 / 0.0882))
    assert int.from_bytes(drive.read_object(Obj.FOLLOWING_ERROR_WINDOW, 0), "little") == math.ceil(0.05 / RAD_PER_COUNT)

    client.load_reference(q, qd)
    client.load_feedforward(J * qdd)
    assert list(client.read_table(Obj.REF_POSITION_TABLE)[:3]) == [rad_to_counts(x) for x in q[:3]]
    client.enable()
    assert client.statusword() == 0x0237
    assert client.state() == Cia402State.OPERATION_ENABLED
    client.arm_trial()
    assert client.trial_status().state == TrialState.ARMED

    plant = DoubleIntegrator(q[0], qd[0])
    taus = run(drive, plant, n)
    status = client.trial_status()
    assert status.state == TrialState.DONE and status.ticks == n
    assert status.recorder == RecorderStatus.COMPLETE and status.recorded_samples == n

    trace = client.read_trace()
    assert len(trace) == n
    for arr in (trace.position_counts, trace.velocity_counts_s, trace.torque_units, trace.torque_fb_units):
        assert arr.dtype == np.int32 and arr.shape == (n,)
    assert list(trace.torque_units) == taus
    ff_units = np.rint(J * qdd / TORQUE_LSB_NM).astype(np.int64)
    assert np.array_equal(trace.torque_units.astype(np.int64) - trace.torque_fb_units, ff_units)
    np.testing.assert_allclose(trace.tau_ff_nm, J * qdd, atol=1e-6)
    # with inverse-dynamics feed-forward the toy tracks within a few hundred counts (what is
    # left comes from the half-tick lag of the difference velocity times Kd and the ZOH)
    err = trace.q_rad - q
    assert np.max(np.abs(err)) < 400 * RAD_PER_COUNT
    assert np.max(np.abs(trace.qd_rad_s - qd)) < 0.01
    np.testing.assert_allclose(trace.q_rad, trace.position_counts * RAD_PER_COUNT)
    np.testing.assert_allclose(trace.tau_nm, trace.torque_units * 1e-6)
    # without feed-forward the same feedback alone lags clearly: the table is what tracks
    client.load_feedforward(np.zeros(n))
    client.arm_trial()
    plant = DoubleIntegrator(q[0], qd[0])
    run(drive, plant, n)
    assert np.max(np.abs(client.read_trace().q_rad - q)) > 10 * np.max(np.abs(err))


def test_enable_disable_fault_reset_flow() -> None:
    drive, client = make()
    client.configure(200.0, 20.0, following_error_rad=1e-4)
    q = np.zeros(20)
    client.load_reference(q, q)
    client.load_feedforward(q)
    client.enable()
    client.arm_trial()
    drive.io_tick(0, 0)
    drive.io_tick(1, 1000)  # 1000 counts ≈ 6e-4 rad > 1e-4 rad window
    assert client.state() == Cia402State.FAULT
    st = client.trial_status()
    assert st.state == TrialState.FAULT and st.fault_cause == FaultCause.FOLLOWING_ERROR
    assert st.recorder == RecorderStatus.STOPPED and st.recorded_samples == 2
    assert len(client.read_trace()) == 2
    with pytest.raises(DriveStateError, match="fault_reset"):
        client.enable()
    client.fault_reset()
    assert client.state() == Cia402State.SWITCH_ON_DISABLED
    assert [e[0] for e in drive.pop_emcy()] == [0x8611, 0x0000]
    client.enable()
    client.disable()
    assert client.state() == Cia402State.SWITCH_ON_DISABLED
    assert drive.io_tick(5, 0) == 0


def test_enable_reports_a_drive_that_does_not_follow() -> None:
    drive, client = make()
    drive.nmt_command(0x80)  # pre-operational still accepts SDO; the 402 machine still runs
    client.enable()
    assert drive.io_tick(0, 0) == 0  # but no torque outside NMT operational

    class Stuck:
        def read_object(self, index: int, sub: int) -> bytes:
            return struct.pack("<H", 0x0240)

        def write_object(self, index: int, sub: int, data: bytes) -> None:
            pass

    with pytest.raises(DriveStateError, match="0x0240"):
        DriveClient(Stuck(), 9).enable()


def test_input_validation() -> None:
    _, client = make()
    with pytest.raises(DriveInputError):
        client.load_reference(np.zeros(5), np.zeros(4))
    client.load_reference(np.zeros(5), np.zeros(5))
    with pytest.raises(DriveInputError, match="5"):
        client.load_feedforward(np.zeros(6))
    with pytest.raises(ValueError):
        client.configure(-1.0, 10.0)
    with pytest.raises(ValueError):
        client.load_feedforward(np.full(5, 1e4))  # 1e4 N·m does not fit int32 µN·m

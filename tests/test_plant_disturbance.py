"""Disturbance torques (paper eq. (37) as interpreted in plant.disturbance)."""

from __future__ import annotations

import numpy as np
import pytest

from plant.disturbance import DisturbanceError, disturbance_torque

N, TS = 501, 1e-3


def test_none_is_zero() -> None:
    d = disturbance_torque("none", 1, 0, N, TS)
    assert d.shape == (N, 4) and not d.any()


def test_repetitive_identical_every_trial_and_seed() -> None:
    a = disturbance_torque("repetitive", 1, 0, N, TS)
    for seed, trial in ((1, 1), (2, 5), (99, 42)):
        np.testing.assert_array_equal(disturbance_torque("repetitive", seed, trial, N, TS), a)
    assert np.abs(a).max() == pytest.approx(2.0, abs=1e-3)
    # one period over the trial: the end equals the start
    np.testing.assert_allclose(a[-1], a[0], atol=1e-12)
    np.testing.assert_allclose(a[0], [0.0, 2.0, 0.0, -2.0], atol=1e-12)
    # explicit period and gain: λ sin(2π t / T + φ_j)
    b = disturbance_torque("repetitive", 0, 0, N, TS, amplitude_nm=1.5, period_s=0.25)
    t = np.arange(N) * TS
    np.testing.assert_allclose(b[:, 1], 1.5 * np.sin(2 * np.pi * t / 0.25 + np.pi / 2), atol=1e-12)


def test_nonrepetitive_differs_per_trial_reproducible_and_bounded() -> None:
    d0 = disturbance_torque("nonrepetitive", 3, 0, N, TS)
    d1 = disturbance_torque("nonrepetitive", 3, 1, N, TS)
    assert np.abs(d0 - d1).max() > 0.1
    np.testing.assert_array_equal(d0, disturbance_torque("nonrepetitive", 3, 0, N, TS))
    assert np.abs(d0 - disturbance_torque("nonrepetitive", 4, 0, N, TS)).max() > 0.1
    for trial in range(20):
        d = disturbance_torque("nonrepetitive", 11, trial, N, TS)
        assert np.abs(d).max() <= 2.4
        assert 0.05 < np.sqrt(np.mean(d**2)) < 1.5  # a few tenths of N·m RMS


def test_both_is_sum_and_bounded() -> None:
    b = disturbance_torque("both", 5, 2, N, TS)
    np.testing.assert_array_equal(
        b, disturbance_torque("repetitive", 5, 2, N, TS) + disturbance_torque("nonrepetitive", 5, 2, N, TS)
    )
    assert np.abs(b).max() <= 4.4


def test_bad_arguments() -> None:
    with pytest.raises(DisturbanceError, match="unknown disturbance kind 'wind'"):
        disturbance_torque("wind", 1, 0, N, TS)
    with pytest.raises(ValueError, match="ts_s"):
        disturbance_torque("both", 1, 0, N, 0.0)
    assert disturbance_torque("both", 1, 0, 0, TS).shape == (0, 4)

"""Property tests of bus.fixedpoint: rounding, saturation, converters, resolution."""

from __future__ import annotations

import math
from fractions import Fraction

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bus import fixedpoint as fp
from bus.units import RAD_PER_COUNT, TORQUE_LSB_NM

int64s = st.integers(min_value=fp.INT64_MIN, max_value=fp.INT64_MAX)
big_ints = st.integers(min_value=-(1 << 80), max_value=1 << 80)


@given(int64s, st.integers(min_value=1, max_value=40))
def test_rshift_round_is_round_half_up_of_exact_rational(x: int, q: int) -> None:
    exact = Fraction(x, 1 << q)
    expected = math.floor(exact + Fraction(1, 2))
    assert fp.rshift_round(x, q) == expected
    assert fp.rshift_round(x, q) == (x + (1 << (q - 1))) >> q  # the textbook form


def test_rshift_round_examples() -> None:
    assert fp.rshift_round(5, 1) == 3  # 2.5 -> 3
    assert fp.rshift_round(-5, 1) == -2  # -2.5 -> -2 (half up)
    assert fp.rshift_round(-7, 1) == -3  # -3.5 -> -3
    assert fp.rshift_round(fp.INT64_MAX, 16) == 1 << 47  # no overflow at the top
    assert fp.rshift_round(123, 0) == 123


@given(big_ints)
def test_sat32_never_wraps(x: int) -> None:
    y = fp.sat32(x)
    assert fp.INT32_MIN <= y <= fp.INT32_MAX
    if fp.INT32_MIN <= x <= fp.INT32_MAX:
        assert y == x
    else:
        assert y == (fp.INT32_MAX if x > 0 else fp.INT32_MIN)


@given(big_ints)
def test_sat16_never_wraps(x: int) -> None:
    y = fp.sat16(x)
    assert fp.INT16_MIN <= y <= fp.INT16_MAX
    assert y == min(max(x, fp.INT16_MIN), fp.INT16_MAX)


@given(st.integers(fp.INT32_MIN, fp.INT32_MAX), st.integers(fp.INT32_MIN, fp.INT32_MAX))
def test_sat_add32(a: int, b: int) -> None:
    assert fp.sat_add32(a, b) == min(max(a + b, fp.INT32_MIN), fp.INT32_MAX)


@given(int64s, int64s)
def test_sat_add64_never_wraps(a: int, b: int) -> None:
    assert fp.sat_add64(a, b) == min(max(a + b, fp.INT64_MIN), fp.INT64_MAX)


@given(st.floats(min_value=0.0, max_value=fp.KP_MAX_NM_PER_RAD * 0.999))
def test_kp_round_trip_within_half_lsb(kp: float) -> None:
    q = fp.kp_to_fixed(kp)
    assert 0 <= q <= fp.INT32_MAX
    assert abs(fp.kp_from_fixed(q) - kp) <= 0.5 * fp.KP_LSB_NM_PER_RAD * (1 + 1e-9)


@given(st.floats(min_value=0.0, max_value=fp.KD_MAX_NMS_PER_RAD * 0.999))
def test_kd_round_trip_within_half_lsb(kd: float) -> None:
    q = fp.kd_to_fixed(kd)
    assert abs(fp.kd_from_fixed(q) - kd) <= 0.5 * fp.KD_LSB_NMS_PER_RAD * (1 + 1e-9)


@given(st.floats(min_value=1.0 / 32768, max_value=1.0))
def test_vel_filter_round_trip(a: float) -> None:
    q = fp.vel_filter_to_fixed(a)
    assert 1 <= q <= 32768
    assert abs(fp.vel_filter_from_fixed(q) - a) <= 0.5 / 32768


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), 1e9])
def test_gain_converters_reject_unrepresentable(bad: float) -> None:
    with pytest.raises(fp.FixedPointRangeError) as exc:
        fp.kp_to_fixed(bad)
    assert "Kp" in str(exc.value)
    with pytest.raises(ValueError):
        fp.kd_to_fixed(bad)


def test_vel_filter_rejects_zero_and_above_one() -> None:
    with pytest.raises(fp.FixedPointRangeError):
        fp.vel_filter_to_fixed(0.0)
    with pytest.raises(fp.FixedPointRangeError):
        fp.vel_filter_to_fixed(1.01)


def test_gain_quantisation_is_tiny_for_typical_gains() -> None:
    for kp in (100.0, 333.3, 1000.0, 2000.0):
        rel = abs(fp.kp_from_fixed(fp.kp_to_fixed(kp)) - kp) / kp
        assert rel <= 0.5 * fp.KP_LSB_NM_PER_RAD / 100.0 < 2e-7
    for kd in (10.0, 22.7, 50.6, 60.0):
        rel = abs(fp.kd_from_fixed(fp.kd_to_fixed(kd)) - kd) / kd
        assert rel < 2e-6
    assert fp.KP_MAX_NM_PER_RAD > 50_000 and fp.KD_MAX_NMS_PER_RAD > 50_000


def test_lsb_constants_consistent_with_units() -> None:
    assert fp.KP_LSB_NM_PER_RAD == pytest.approx(TORQUE_LSB_NM / RAD_PER_COUNT / 65536)
    assert fp.kp_to_fixed(1.0) == round(RAD_PER_COUNT / TORQUE_LSB_NM * 65536)


def test_torque_limit_and_permille() -> None:
    assert fp.torque_limit_units(3000, 88_200) == 264_600_000  # 264.6 N·m in µN·m
    assert fp.torque_units_to_permille(264_600_000, 88_200) == 3000
    assert fp.torque_units_to_permille(-44_100, 88_200) == 0  # -0.5 ‰ rounds half up
    assert fp.torque_units_to_permille(-44_101, 88_200) == -1
    assert fp.torque_units_to_permille(fp.INT32_MAX, 1) == fp.INT16_MAX  # saturates
    assert fp.torque_nm_to_permille(264.6, 88_200) == 3000
    assert fp.permille_to_nm(3000, 88_200) == pytest.approx(264.6)


def test_rate_q12() -> None:
    assert fp.rate_q12_from_period_us(1000) == 1000 * 4096
    assert fp.rate_q12_from_period_us(500) == 2000 * 4096
    assert fp.rate_q12_from_period_us(3) == round(1e6 / 3 * 4096)
    with pytest.raises(ValueError):
        fp.rate_q12_from_period_us(0)

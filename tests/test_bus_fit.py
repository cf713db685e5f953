"""The cyclic exchange against the fieldbus (bus.cyclic.cyclic_bus_fit) and the experiment options
of the pdo transport (TOML keys, validation, refusal before anything moves)."""

from __future__ import annotations

from pathlib import Path

import pytest

from bus.busload import DEFAULT_BITRATE_BPS, frame_bits, frame_bits_worst_case
from bus.cyclic import cyclic_bus_fit, nm_to_permille_array, permille_to_nm_array
from host.experiment.config import ConfigError, build_config


def test_one_period_of_sync_four_rpdo_four_tpdo() -> None:
    fit = cyclic_bus_fit(1e-3)
    assert fit.bitrate_bps == DEFAULT_BITRATE_BPS == 1_000_000
    assert fit.bits_nominal == frame_bits(0) + 4 * 2 * frame_bits(6) == 807
    assert fit.bits_worst_case == frame_bits_worst_case(0) + 8 * frame_bits_worst_case(6) == 975
    assert fit.fits and fit.margin_percent == pytest.approx(2.5)
    assert fit.frames_per_cycle == 9
    assert int(fit.max_rate_hz) == 1025 and fit.min_bitrate_bps == 975_000
    half = cyclic_bus_fit(1e-3, 500_000)
    assert not half.fits and half.load_percent_worst_case == pytest.approx(195.0)
    assert cyclic_bus_fit(2e-3, 500_000).fits
    assert not cyclic_bus_fit(1e-3, tpdo_bytes=8).fits  # a statusword in every TPDO: 105.5 %
    assert "does NOT fit" in half.message() and "fits with 2.5 % margin" in fit.message()


def test_permille_conversion_is_nearest_and_saturated() -> None:
    got = nm_to_permille_array([0.0441, 0.0442, -0.0442, 1e6, -1e6])
    assert got.tolist() == [0, 1, -1, 32767, -32768]
    assert permille_to_nm_array([1, -18]).tolist() == pytest.approx([0.0882, -1.5876])


def test_pdo_options_from_toml_and_their_checks(tmp_path: Path) -> None:
    f = tmp_path / "exp.toml"
    f.write_text('ff_transport = "pdo"\nfieldbus_bitrate = 500000\nts_s = 0.002\n')
    cfg = build_config(f)
    assert cfg.ff_transport == "pdo" and cfg.fieldbus_bitrate == 500_000
    assert build_config(None).ff_transport == "table"
    with pytest.raises(ConfigError, match="does not fit the fieldbus"):
        build_config(None, {"ff_transport": "pdo", "fieldbus_bitrate": 500_000})
    forced = build_config(None, {"ff_transport": "pdo", "fieldbus_bitrate": 500_000, "force_bus_fit": True})
    assert forced.force_bus_fit
    # the table transport does not use the fieldbus per tick: nothing to check
    assert build_config(None, {"fieldbus_bitrate": 125_000}).ff_transport == "table"
    with pytest.raises(ConfigError, match="ff_transport"):
        build_config(None, {"ff_transport": "sdo"})
    with pytest.raises(ConfigError, match="fieldbus_bitrate"):
        build_config(None, {"fieldbus_bitrate": 0})

"""Names the command line offers (kept import-light so every role starts fast)."""

from __future__ import annotations

#: learning laws, see :mod:`host.ilc`
LAWS: tuple[str, ...] = ("pd-ilc", "pd-ol", "p-ol", "d-ilc", "q-ilc", "no-ilc")
#: motion laws, see :mod:`host.trajectory`
PROFILES: tuple[str, ...] = ("ruckig", "poly4567", "poly5")
#: disturbance kinds, see :mod:`plant.disturbance`
DISTURBANCES: tuple[str, ...] = ("none", "repetitive", "nonrepetitive", "both")
#: gain presets, see :data:`host.ilc.GAIN_PRESETS`
GAIN_PRESET_NAMES: tuple[str, ...] = ("normalized", "paper")

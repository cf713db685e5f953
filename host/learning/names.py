"""The names of the learning laws and gain presets: the one list the command line, the
configuration and the law registry (:mod:`host.learning.ilc`) share.  Import-light on
purpose: every role parses the command line, and the laws themselves pull in scipy."""

from __future__ import annotations

#: learning laws; :func:`host.learning.ilc.make_law` builds each (its registry is checked
#: against this tuple at import)
LAWS: tuple[str, ...] = ("pd-ilc", "pd-ol", "p-ol", "d-ilc", "q-ilc", "no-ilc")
#: gain presets, see :data:`host.learning.ilc.GAIN_PRESETS`
GAIN_PRESET_NAMES: tuple[str, ...] = ("normalized", "paper")

"""The time operators a learning law uses, with their exact transposes (for its iteration map):
re-exported from :mod:`host.learning.signals`.

Owns nothing of its own: ``lead(x, m)`` (y[n] = x[n+m], the last value repeated), ``lead_t``,
``backward_difference(x, ts_s)`` ((x[n] − x[n−1])/Ts, 0 at n = 0), ``backward_difference_t`` and
``ZeroPhaseFilter(cutoff_hz, order, ts_s)`` (a Butterworth filter run forward and backward, with
``.transpose``).  Signals are (N, J) arrays, time along axis 0.
"""

from __future__ import annotations

from host.learning.signals import ZeroPhaseFilter, backward_difference, backward_difference_t, lead, lead_t

__all__ = ["ZeroPhaseFilter", "backward_difference", "backward_difference_t", "lead", "lead_t"]

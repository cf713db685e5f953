"""The drive's fixed-point motion profile generator: a trapezoidal position profile and a stop
ramp, one step per control cycle.

Owns :class:`ProfileGenerator`, the set-point generator of profile position (0x6060 = 1), the
position hold of homing (6), the integration of cyclic synchronous velocity (9) and the
deceleration ramps of quick stop and halt.  Formats (:mod:`bus.fixedpoint`, ``PROFILE_Q`` = 16):
position demand ``p`` in counts Q16, velocity ``v`` in counts per control cycle Q16 (signed),
acceleration and deceleration in counts per cycle² Q16 (>= 1); the rates of the objects
(0x6081 counts/s, 0x6083/0x6084/0x6085 counts/s²) are converted with
:func:`bus.fixedpoint.per_tick_q16` for the control period 0x2300.

One step towards a target ``T`` (:meth:`ProfileGenerator.step_to`), with ``d = T·2^16 − p`` and
the velocity ``u = v·sign(d)`` along it:

* moving away from the target (``u < 0``): brake, ``u' = min(u + dec, 0)``;
* otherwise ``u' = min(u + acc, v_max, (isqrt(8·dec·|d| + dec²) − dec) // 2)`` -- accelerate,
  cruise, or the largest velocity from which braking by ``dec`` per cycle (moving ``u'``, then
  ``u' − dec``, ...) stops within ``|d|`` (``u'²/(2·dec) + u'/2 <= |d|``) -- but never below
  ``u − dec`` (the deceleration limit; a target that came too close by a change of set-point is
  overshot and approached again);
* if ``|d| <= u'`` the target is reached this cycle: ``p = T·2^16``, ``v = 0`` (the profile always
  ends exactly on the target); else ``p += u'·sign(d)``, ``v = u'·sign(d)``.

A stop (:meth:`ProfileGenerator.step_stop`) lowers ``|v|`` by ``dec`` per cycle to 0, moving ``p``
by the new velocity.  Everything is integer arithmetic with an explicit rounding (``isqrt``
floors, :func:`bus.fixedpoint.profile_position_counts` rounds half up) and saturation (the
position stays within the int32 counts); ``8·dec·|d|`` is formed exactly (up to 2^93: a C port
needs a 128-bit product there).
"""

from __future__ import annotations

import logging
from math import isqrt

from bus import fixedpoint as fp

logger = logging.getLogger(__name__)


class ProfileGenerator:
    """Position demand and velocity of one drive's profile (see the module docstring).

    :ivar p: position demand, counts Q16.
    :ivar v: velocity, counts per cycle Q16 (signed).
    """

    def __init__(self) -> None:
        self.p = 0
        self.v = 0

    def reset(self, position_counts: int, velocity_q16: int = 0) -> None:
        """Start at ``position_counts`` [counts] with velocity ``velocity_q16`` [counts/cycle Q16]."""
        self.p = int(position_counts) << fp.PROFILE_Q
        self.v = int(velocity_q16)

    @property
    def position_counts(self) -> int:
        """The position demand, int32 counts (rounded half up)."""
        return fp.profile_position_counts(self.p)

    @property
    def standstill(self) -> bool:
        return self.v == 0

    def shift(self, delta_counts: int) -> None:
        """Move the demand by ``delta_counts`` (homing redefines the position)."""
        self.p = fp.sat(self.p + (int(delta_counts) << fp.PROFILE_Q), fp.PROFILE_POS_MIN, fp.PROFILE_POS_MAX)

    def _move(self, v: int) -> None:
        self.v = v
        self.p = fp.sat(self.p + v, fp.PROFILE_POS_MIN, fp.PROFILE_POS_MAX)

    def step_to(self, target_counts: int, v_max_q16: int, acc_q16: int, dec_q16: int) -> bool:
        """One cycle towards ``target_counts``; True when the demand is on the target at rest."""
        d = (int(target_counts) << fp.PROFILE_Q) - self.p
        if d == 0 and self.v == 0:
            return True
        acc, dec, v_max = max(int(acc_q16), 1), max(int(dec_q16), 1), max(int(v_max_q16), 0)
        if d > 0:
            s = 1
        elif d < 0:
            s = -1
        else:  # on the target but moving: brake (and come back)
            s = -1 if self.v > 0 else 1
        dist = abs(d)
        u = self.v * s
        if u < 0:
            u_new = min(u + dec, 0)
        else:
            u_new = min(u + acc, v_max, (isqrt(8 * dec * dist + dec * dec) - dec) // 2)
            u_new = max(u_new, u - dec)
            if dist <= u_new:
                self.p = int(target_counts) << fp.PROFILE_Q
                self.v = 0
                return True
        self._move(s * u_new)
        return False

    def step_stop(self, dec_q16: int) -> bool:
        """One cycle of a stop ramp; True when at rest."""
        if self.v == 0:
            return True
        dec = max(int(dec_q16), 1)
        if self.v > 0:
            self._move(max(self.v - dec, 0))
        else:
            self._move(min(self.v + dec, 0))
        return self.v == 0

    def step_velocity(self, v_q16: int) -> None:
        """One cycle at velocity ``v_q16`` (cyclic synchronous velocity: the demand integrates the
        target velocity)."""
        self._move(int(v_q16))

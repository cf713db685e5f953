"""Robot parameters: geometry, lumped mass model and true-plant configuration (SI units).

This module owns every physical number the plant and the host's nominal model use.
Each value carries the source tag of docs/robot-model.md:

* **[S]** taken from a named source (S1 = Li et al. 2022 Table 1, S3 Codourey, S4 Olsson,
  S7 Yaskawa Sigma-II manual),
* **[D]** derived from [S]/[P] values,
* **[P]** proposed (plausible, not published).

Drivetrain (lead decision, deviating from docs/robot-model.md §2.3): reducer n = 10 (= bus.units.GEAR_RATIO)
with a **3 kW class motor** instead of docs/robot-model.md 1 kW, so that the paper's 0.15 s single
journeys are feasible: rotor 7.0e-4 kg·m² + reducer input 0.16e-4 kg·m², peak motor torque
29.4 N·m, max speed 5000 rpm.  [P] "3 kW class, Sigma-II SGMSH-30A-like values, not re-checked".

Conventions (docs/robot-model.md §3.1): base frame z up, motor axes in z = 0, joint angle q = 0 with the
inner arm horizontal pointing outward, positive downward.  Sub-platform coordinates
Y = (x, y, z_u, z_l); task coordinates X = (x, y, z, θ) with (x, y, z) the TCP on the lower
sub-platform.  Limbs 1, 3 (index 0, 2) drive the upper sub-platform, limbs 2, 4 (index 1, 3)
the lower one.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

logger = logging.getLogger(__name__)

#: standard gravity, m/s² (gravity vector is (0, 0, -G_MS2) in the base frame)
G_MS2: float = 9.81

#: limbs whose ball bar sits on the upper sub-platform (0-based limb index -> True)
LIMB_ON_UPPER: tuple[bool, bool, bool, bool] = (True, False, True, False)


@dataclass(frozen=True)
class Geometry:
    """Kinematic geometry (docs/robot-model.md §2.3, §3).  Lengths in m, angles in rad."""

    #: inner arm length, motor axis to elbow-bar midpoint [S1 Table 1]
    l_a: float = 0.296
    #: outer arm (rod) length, ball centre to ball centre [S1 Table 1]
    l_b: float = 0.600
    #: motor-axis offset from the base centre (axis tangent to a circle of radius R) [P]
    R: float = 0.200
    #: sub-platform ball-bar midpoint offset from the platform axis [P]
    r: float = 0.060
    #: limb azimuths φ_i, rad (0°, 90°, 180°, 270°) [P]
    azimuths_rad: tuple[float, float, float, float] = (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi)
    #: nominal gap z_u - z_l at θ = 0, m [P]
    d0: float = 0.050
    #: screw lead, m per revolution [P]
    h: float = 0.040
    #: TCP offset below the lower-platform ball plane, m [P]
    e: float = 0.0

    def __post_init__(self) -> None:
        for name in ("l_a", "l_b", "R", "h"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"Geometry.{name} must be > 0, got {getattr(self, name)!r}")
        if len(self.azimuths_rad) != 4:
            raise ValueError("Geometry.azimuths_rad needs 4 limb azimuths")


@dataclass(frozen=True)
class MassModel:
    """Lumped mass model of docs/robot-model.md §4 (kg, m, kg·m²).

    Derived quantities (properties) follow the lumping rules: the forearm mass of each limb
    is split, ``rho`` at the elbow and ``1 - rho`` at the sub-platform; the inner arm is a
    rigid link with inertia ``I_a`` about the motor axis and COM at ``l_c``.
    """

    #: upper sub-platform mass [S1 Table 1]
    m_up: float = 0.855
    #: lower sub-platform mass incl. screw shaft / TCP hardware [S1 Table 1]
    m_low: float = 1.080
    #: inner arm mass [S1 Table 1]
    m_a: float = 0.842
    #: inner-arm inertia about the motor axis, m_a l_a²/3 = 0.0246 kg·m² [P, S3 convention]
    I_a: float = 0.842 * 0.296**2 / 3.0
    #: inner-arm COM distance from the motor axis, l_a/2 [P, S3 convention]
    l_c: float = 0.148
    #: outer arm mass per limb (rod pair + cups) [S1 Table 1; per-limb reading P]
    m_fa: float = 0.073
    #: share of the forearm mass lumped at the elbow (1/2 S3, 2/3 S4)
    rho: float = 0.5
    #: reducer ratio [P] (= bus.units.GEAR_RATIO)
    n: float = 10.0
    #: reducer efficiency [P]
    eta: float = 0.90
    #: motor rotor + reducer input inertia, kg·m²: 7.0e-4 + 0.16e-4
    #: [P] 3 kW class, Sigma-II SGMSH-30A-like values, not re-checked (lead decision)
    J_m: float = 7.0e-4 + 0.16e-4
    #: payload on the lower sub-platform, kg [P]
    payload: float = 0.0
    #: end-effector (screw shaft + tool) spin inertia about z, kg·m² (0 in the nominal model) [P]
    I_ee: float = 0.0
    #: gravitational acceleration magnitude, m/s²
    g: float = G_MS2

    def __post_init__(self) -> None:
        for name in ("m_up", "m_low", "m_a", "I_a", "m_fa", "n", "eta", "J_m", "payload", "I_ee", "g"):
            if getattr(self, name) < 0.0:
                raise ValueError(f"MassModel.{name} must be >= 0, got {getattr(self, name)!r}")
        if not 0.0 <= self.rho <= 1.0:
            raise ValueError(f"MassModel.rho must be in [0, 1], got {self.rho!r}")

    @property
    def m_up_eff(self) -> float:
        """Upper sub-platform point mass incl. 2 (1-ρ) m_fa, kg [D]."""
        return self.m_up + 2.0 * (1.0 - self.rho) * self.m_fa

    @property
    def m_low_eff(self) -> float:
        """Lower sub-platform point mass incl. 2 (1-ρ) m_fa and payload, kg [D]."""
        return self.m_low + 2.0 * (1.0 - self.rho) * self.m_fa + self.payload

    def joint_inertia(self, l_a: float) -> float:
        """I_b = I_a + ρ m_fa l_a² + n² J_m for arm length ``l_a`` (m), kg·m²."""
        return self.I_a + self.rho * self.m_fa * l_a**2 + self.n**2 * self.J_m

    def arm_gravity_coefficient(self, l_a: float) -> float:
        """(m_a l_c + ρ m_fa l_a) g, N·m: the arm gravity torque is −this·cos q [D]."""
        return (self.m_a * self.l_c + self.rho * self.m_fa * l_a) * self.g

    def spin_equivalent_mass(self, h: float) -> float:
        """Equivalent mass of the tool spin on the relative z motion, (2π/h)² I_ee, kg [D]
        (≈ 4.9 kg for I_ee = 2e-4 kg·m², h = 0.04 m/rev)."""
        return (2.0 * math.pi / h) ** 2 * self.I_ee


#: ±20 % joint-to-joint spread of the Coulomb friction, fixed factors per joint [P]
COULOMB_SPREAD: tuple[float, float, float, float] = (1.12, 0.85, 0.95, 1.18)
#: ±20 % joint-to-joint spread of the viscous friction, fixed factors per joint [P]
VISCOUS_SPREAD: tuple[float, float, float, float] = (0.88, 1.15, 1.05, 0.82)


@dataclass(frozen=True)
class TruePlantConfig:
    """The emulated robot: a mass model plus effects the nominal model lacks (docs/robot-model.md §5.1).

    Friction per joint (joint side): ``τ_f = F(q̇) tanh(q̇ / v_smooth) + F_v q̇`` with
    ``F(q̇) = F_c (1 + (r_s - 1) exp(-(q̇/v_s)²))`` (Stribeck; ``r_s = 1`` switches it off).
    The commanded torque is clamped to ``±joint_torque_limit_nm`` before the disturbance
    (an external torque) is added.  Not modelled: screw efficiency, current-loop lag,
    transport delay, encoder noise (docs/robot-model.md §5.1 lists them as optional).
    """

    #: mass model of the emulated robot
    mass: MassModel = field(default_factory=MassModel)
    #: geometry of the emulated robot (same as the nominal one)
    geometry: Geometry = field(default_factory=Geometry)
    #: Coulomb friction per joint, N·m (1.5 N·m × spread) [P]
    coulomb_nm: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    #: viscous friction per joint, N·m·s/rad (0.4 × spread) [P]
    viscous_nm_s_per_rad: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    #: smoothing velocity of the Coulomb term, rad/s [P]
    friction_smoothing_rad_s: float = 0.01
    #: Stribeck ratio F_s/F_c (1.0 = off; docs/robot-model.md §5.1 suggests 1.3 as an option) [P]
    stribeck_ratio: float = 1.0
    #: Stribeck velocity, rad/s [P]
    stribeck_velocity_rad_s: float = 0.05
    #: peak motor torque, N·m [P] 3 kW class (SGMSH-30A-like), lead decision
    tau_motor_peak_nm: float = 29.4
    #: maximum motor speed, rpm [P] 3 kW class
    motor_speed_max_rpm: float = 5000.0
    #: clamp the commanded joint torque to ±joint_torque_limit_nm
    torque_limit_enabled: bool = True

    def __post_init__(self) -> None:
        if len(self.coulomb_nm) != 4 or len(self.viscous_nm_s_per_rad) != 4:
            raise ValueError("friction needs 4 values per parameter (one per joint)")
        if not self.friction_smoothing_rad_s > 0.0:
            raise ValueError("friction_smoothing_rad_s must be > 0")
        if not self.stribeck_velocity_rad_s > 0.0:
            raise ValueError("stribeck_velocity_rad_s must be > 0")
        if not self.tau_motor_peak_nm > 0.0:
            raise ValueError("tau_motor_peak_nm must be > 0")

    @property
    def joint_torque_limit_nm(self) -> float:
        """Joint-side torque limit n η τ_peak, N·m (264.6 N·m with the defaults) [D]."""
        return self.mass.n * self.mass.eta * self.tau_motor_peak_nm

    @property
    def joint_speed_limit_rad_s(self) -> float:
        """Joint speed limit = max motor speed / n, rad/s (52.4 rad/s) [D]."""
        return self.motor_speed_max_rpm * 2.0 * math.pi / 60.0 / self.mass.n

    @property
    def has_friction(self) -> bool:
        """True if any friction coefficient is non-zero."""
        return any(c != 0.0 for c in self.coulomb_nm) or any(v != 0.0 for v in self.viscous_nm_s_per_rad)


def nominal_mass_model() -> MassModel:
    """The host's nominal model (docs/robot-model.md §4): ρ = 1/2, no payload, no tool spin inertia."""
    return MassModel()


def robot_md_mass_model() -> MassModel:
    """Nominal model with docs/robot-model.md original 1 kW drivetrain (J_m = 1.9e-4 kg·m², S7 SGMSH-10A).

    Only for cross-checking numbers quoted in docs/robot-model.md (e.g. §5.4 loads); gravity terms do
    not depend on J_m.
    """
    return replace(MassModel(), J_m=1.74e-4 + 0.16e-4)


def _scaled4(k: float, v: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    """``k`` times each of the four joint values."""
    return k * v[0], k * v[1], k * v[2], k * v[3]


def default_true_plant() -> TruePlantConfig:
    """The emulated robot of docs/robot-model.md §5.1 (all differences [P]).

    * forearm lumping ρ = 2/3 (S4) vs nominal 1/2
    * inner-arm inertia +10 %, COM l_c = 0.135 m (heavy hub)
    * platform masses +5 %
    * payload 0.2 kg on the lower sub-platform
    * tool spin inertia I_ee = 2e-4 kg·m² coupled through the screw
    * Coulomb 1.5 N·m, viscous 0.4 N·m·s/rad per joint, with the fixed ±20 % spread factors
      :data:`COULOMB_SPREAD`, :data:`VISCOUS_SPREAD`
    * joint torque limit n η τ_peak = 264.6 N·m
    """
    nom = nominal_mass_model()
    mass = replace(
        nom,
        rho=2.0 / 3.0,
        I_a=1.10 * nom.I_a,
        l_c=0.135,
        m_up=1.05 * nom.m_up,
        m_low=1.05 * nom.m_low,
        payload=0.2,
        I_ee=2e-4,
    )
    return TruePlantConfig(
        mass=mass,
        geometry=Geometry(),
        coulomb_nm=_scaled4(1.5, COULOMB_SPREAD),
        viscous_nm_s_per_rad=_scaled4(0.4, VISCOUS_SPREAD),
    )


@dataclass(frozen=True)
class PlantScales:
    """Plant uncertainty: dimensionless factors on the emulated robot's parameters (1.0 = the robot
    of :func:`default_true_plant`), for Monte Carlo robustness studies.  The host's nominal model
    does not change: the factors make the emulated robot differ more (or less) from it.

    * ``inertia_scale`` — the rotational inertias: inner arm ``I_a``, rotor + reducer ``J_m``, tool
      spin ``I_ee``;
    * ``mass_scale`` — the link and platform masses: ``m_up``, ``m_low``, ``m_a``, ``m_fa`` (gravity
      and the translational inertia of the platforms change with them);
    * ``friction_scale`` — Coulomb and viscous friction of every joint;
    * ``payload_scale`` — the payload on the lower sub-platform (0 = none).
    """

    inertia_scale: float = 1.0
    mass_scale: float = 1.0
    friction_scale: float = 1.0
    payload_scale: float = 1.0

    def __post_init__(self) -> None:
        for name in ("inertia_scale", "mass_scale", "friction_scale", "payload_scale"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"plant.{name} must be a finite number, got {v!r}")
        for name in ("inertia_scale", "mass_scale"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"plant.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("friction_scale", "payload_scale"):
            if getattr(self, name) < 0.0:
                raise ValueError(f"plant.{name} must be >= 0, got {getattr(self, name)!r}")

    @property
    def identity(self) -> bool:
        """True when every factor is 1 (the robot as built)."""
        return self == PlantScales()

    def as_tuple(self) -> tuple[float, float, float, float]:
        """(inertia, mass, friction, payload) factors."""
        return (float(self.inertia_scale), float(self.mass_scale), float(self.friction_scale), float(self.payload_scale))


def scaled_true_plant(base: TruePlantConfig, scales: PlantScales) -> TruePlantConfig:
    """``base`` with the factors of ``scales`` applied (``base`` itself when they are all 1)."""
    if scales.identity:
        return base
    ki, km, kf, kp = scales.as_tuple()
    m = base.mass
    mass = replace(
        m,
        I_a=ki * m.I_a,
        J_m=ki * m.J_m,
        I_ee=ki * m.I_ee,
        m_up=km * m.m_up,
        m_low=km * m.m_low,
        m_a=km * m.m_a,
        m_fa=km * m.m_fa,
        payload=kp * m.payload,
    )
    return replace(
        base,
        mass=mass,
        coulomb_nm=_scaled4(kf, base.coulomb_nm),
        viscous_nm_s_per_rad=_scaled4(kf, base.viscous_nm_s_per_rad),
    )


def nominal_plant_config(torque_limit_enabled: bool = True) -> TruePlantConfig:
    """A plant built on the nominal model without friction (for tests and model checks)."""
    return TruePlantConfig(mass=nominal_mass_model(), geometry=Geometry(), torque_limit_enabled=torque_limit_enabled)

"""Test harness: faults a foreign master causes on a running robot (``ilcrig robot``, or the
:class:`robot_util.VirtualRobot`), one scenario each, on the robot as it stands.

:class:`FaultMaster` is the :class:`robot_util.LockstepMaster` (raw RPDO1 + SYNC per period, the
four TPDO1 back) plus what a scenario needs: every drive back to its defaults (NMT reset node) and
the robot's fault reset (:meth:`FaultMaster.fresh`), a period stepped by SYNC alone and confirmed
by the plant node's period counter (:meth:`FaultMaster.sync_only`: for drives that send no TPDO
any more), the robot's joints, brakes and periods by SDO, a glide back to where the first scenario
began (:meth:`FaultMaster.enable_here`), and a motion around that pose (:meth:`FaultMaster.sway`:
the tool up and down, so a fault comes mid-motion).

Each scenario (:data:`SCENARIOS`) enables the robot in CSP, glides it to where the first scenario
began (:meth:`FaultMaster.enable_here`: none depends on the ones before), moves it, causes its fault, steps on
until the drives' reaction has made the robot torque-free, and returns what happened
(:class:`FaultResult`: the EMCYs, the states, the brakes, whether the robot stood still, the time
from the cause to the first EMCY).  The drives' settings of each scenario choose a different
reaction (0x6007 abort connection, 0x605A quick stop, 0x1029 NMT state), so together they show
each is honoured.  Every wait is for a frame or an answer, bounded by :data:`WAIT_S`.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from robot_util import DRIVES, PLANT_ID, LockstepMaster

from bus import units
from plant.kinematics import inverse_kinematics

#: bound of every wait [s] (× ILCRIG_TIMEOUT_SCALE)
WAIT_S = 60.0 * units.timeout_scale()
#: the master's heartbeat node id and the drives' consumer time of it [ms]
MASTER_ID = 127
CONSUMER_MS = round(300 * units.timeout_scale())
#: the communication cycle period the SYNC-stop scenario promises [µs] (lost after 1.5 ×)
SYNC_PERIOD_US = round(200_000 * units.timeout_scale())
#: the RPDO deadline of the RPDO-stop scenario [ms]: that many control periods of 1 ms
RPDO_DEADLINE_MS = 50
#: the drives' heartbeat [ms]: their NMT state, seen on the bus
HEARTBEAT_MS = 50
#: control periods of the glide back to the first scenario's pose (:meth:`FaultMaster.enable_here`)
GLIDE_PERIODS = 300
SWITCH_ON_DISABLED, FAULT = (0x4F, 0x40), (0x4F, 0x08)


@dataclass
class FaultResult:
    """What one scenario showed (see the module docstring).

    :ivar emcy: the drives' EMCYs after the cause, per node (data bytes)
    :ivar robot_emcy: the plant node's EMCYs after the cause (data bytes)
    :ivar latency_ms: from the cause to the first EMCY of the fault [ms] (0: not measured -- an
        end stop is hit in the period that reaches it, an NMT STOP sends no EMCY)
    :ivar periods: control periods from the cause until the robot was torque-free
    :ivar states: per drive the CiA 402 statusword after the reaction (by SDO or TPDO)
    :ivar nmt: per drive its NMT state after the reaction (from its heartbeat)
    :ivar brakes: 0x2450:12 after the reaction
    :ivar still: the robot's joints did not move over the periods after the reaction
    :ivar objects: per drive (0x1003:1, 0x603F) after the reaction, where readable
    """

    emcy: dict[int, list[bytes]] = field(default_factory=dict)
    robot_emcy: list[bytes] = field(default_factory=list)
    latency_ms: float = 0.0
    periods: int = 0
    states: dict[int, int] = field(default_factory=dict)
    nmt: dict[int, str] = field(default_factory=dict)
    brakes: int = 0
    still: bool = False
    objects: dict[int, tuple[int, int]] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)


class FaultMaster(LockstepMaster):
    """The lockstep master with the helpers of the scenarios (module docstring).

    :ivar home: the joint counts where the first scenario began (every scenario starts there)
    """

    home: dict[int, int] | None = None

    def u(self, index: int, sub: int, signed: bool = False) -> int:
        """An object of the plant node, by SDO."""
        return int.from_bytes(self.plant.sdo.upload(index, sub), "little", signed=signed)

    def joints(self) -> dict[int, int]:
        """The robot's joint positions [counts] (0x2451)."""
        return {n: self.u(0x2451, n, signed=True) for n in DRIVES}

    def brakes(self) -> int:
        return self.u(0x2450, 12)

    def periods(self) -> int:
        return self.u(0x2450, 4)

    def drive_sdo(self, node: int, index: int, sub: int, fmt: str, value: int) -> None:
        self.drives[node].sdo.download(index, sub, struct.pack("<" + fmt, value))

    def drive_u(self, node: int, index: int, sub: int, fmt: str) -> int:
        return int(struct.unpack("<" + fmt, self.drives[node].sdo.upload(index, sub))[0])

    def fresh(self) -> None:
        """Every drive back to its defaults (NMT reset node, boot-ups seen), the robot's fault reset,
        the EMCYs forgotten."""
        with self._cond:
            self.booted -= set(DRIVES)
        for node in DRIVES:
            self.drives[node].nmt.send_command(0x81)
        with self._cond:
            if not self._cond.wait_for(lambda: self.booted >= set(DRIVES), WAIT_S):
                raise TimeoutError(f"booted again: {sorted(self.booted)}")
        if self.u(0x2450, 3) == 2:  # the robot in fault
            self.plant.sdo.download(0x2450, 2, b"\x01")
        with self._cond:
            self.emcy.clear()

    def sync_only(self) -> int:
        """One control period by a SYNC alone, confirmed by the plant node's period counter."""
        before = self.periods()
        self.network.send_message(0x080, b"")
        deadline = time.monotonic() + WAIT_S
        while (now := self.periods()) <= before:
            if time.monotonic() > deadline:
                raise TimeoutError("the robot did not step its period")
        return now

    def enable_here(self, before_start: Callable[[], None] | None = None) -> dict[int, int]:
        """CSP with RPDO1/TPDO1 (:meth:`configure`), NMT start, Operation enabled where the robot
        stands, then a glide back to where the first scenario began (:attr:`home`); those joint
        counts.  So every scenario starts from one pose, whatever the ones before it did: how many
        periods a scenario runs depends on the machine's speed (a consumer time is wall-clock time),
        and where a sway stopped decided which limit a later move met first."""
        self.configure()
        if before_start is not None:
            before_start()
        self.start()
        here = self.joints()
        self.enable(here)
        if self.home is None:
            self.home = here
        home = self.home
        for k in range(1, GLIDE_PERIODS + 1):
            s = (1.0 - np.cos(np.pi * k / GLIDE_PERIODS)) / 2.0
            self.cycle({n: (0x0F, here[n] + round(s * (home[n] - here[n]))) for n in DRIVES})
        return dict(home)

    def sway(
        self, here: dict[int, int], amplitude_m: float = 0.01, period: int = 800
    ) -> Callable[[int], dict[int, tuple[int, int]]]:
        """Period k → (controlword, target) per drive: the tool up and down by ``amplitude_m``
        around where it stands (joint offsets by the robot model's IK)."""
        x0 = np.array([self.u(0x2452, j, signed=True) * 1e-6 for j in (1, 2, 3, 4)])
        q0 = inverse_kinematics(x0)
        k_all = np.arange(period)
        x = np.repeat(x0[None, :], period, axis=0)
        x[:, 2] -= amplitude_m * np.sin(2 * np.pi * k_all / period)
        dq = np.rint((inverse_kinematics(x) - q0) / units.RAD_PER_COUNT).astype(np.int64)

        def targets(k: int) -> dict[int, tuple[int, int]]:
            row = dq[k % period]
            return {n: (0x0F, here[n] + int(row[n - 1])) for n in DRIVES}

        return targets

    def drive_emcy(self, since: int, code: int) -> dict[int, list[bytes]]:
        """The drives' EMCYs with ``code`` received after the first ``since``."""
        with self._cond:
            out: dict[int, list[bytes]] = {}
            for cob, data in self.emcy[since:]:
                node = cob - 0x080
                if node in DRIVES and data[:2] == struct.pack("<H", code):
                    out.setdefault(node, []).append(data)
            return out

    def after_reaction(self, result: FaultResult, step: Callable[[], None]) -> None:
        """The robot after the drives reacted: brakes, and whether three more periods moved it."""
        step()
        before = self.joints()
        for _ in range(3):
            step()
        result.brakes = self.brakes()
        result.still = self.joints() == before

    def nmt_states(self, expect: str | None = None) -> dict[int, str]:
        """Every drive's NMT state from its heartbeats: the next one, or with ``expect`` the first
        that says it within WAIT_S (a heartbeat already on its way when an NMT command went out says
        the state before the command)."""
        out = {}
        for n in DRIVES:
            deadline = time.monotonic() + WAIT_S
            state = self.drives[n].nmt.wait_for_heartbeat(WAIT_S)
            while expect is not None and state != expect and time.monotonic() < deadline:
                state = self.drives[n].nmt.wait_for_heartbeat(WAIT_S)
            out[n] = state
        return out

    def errors(self) -> dict[int, tuple[int, int]]:
        """Per drive (0x1003:1 newest error, 0x603F error code)."""
        return {n: (self.drive_u(n, 0x1003, 1, "I"), self.drive_u(n, 0x603F, 0, "H")) for n in DRIVES}


def _for_every_drive(m: FaultMaster, *writes: tuple[int, int, str, int]) -> None:
    for node in DRIVES:
        for index, sub, fmt, value in writes:
            m.drive_sdo(node, index, sub, fmt, value)


def _until(predicate: Callable[[], bool], step: Callable[[], Any], what: str, limit: int = 100_000) -> int:
    """Step until ``predicate``; the number of steps."""
    deadline = time.monotonic() + WAIT_S
    n = 0
    while not predicate():
        if n >= limit or time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not within {n} periods")
        step()
        n += 1
    return n


def heartbeat_lost(m: FaultMaster) -> FaultResult:
    """The master's heartbeat stops mid-motion (consumer 0x1016); the reaction chosen: 0x6007 = 3
    quick stop, 0x605A = 2 (ramp, then Switch on disabled), 0x1029:1 = 1 (NMT unchanged)."""
    m.fresh()
    _for_every_drive(
        m,
        (0x1016, 1, "I", MASTER_ID << 16 | CONSUMER_MS),
        (0x6007, 0, "h", 3),
        (0x605A, 0, "h", 2),
        (0x1029, 1, "B", 1),
        (0x1017, 0, "H", HEARTBEAT_MS),
    )
    beat = m.network.send_periodic(0x700 + MASTER_ID, b"\x05", 0.02)
    try:
        here = m.enable_here()
        move = m.sway(here)
        k = 0
        for k in range(100):
            m.cycle(move(k))
    finally:
        beat.stop()
    t0, since, res = time.monotonic(), len(m.emcy), FaultResult()
    state: dict[int, tuple[int, int]] = {}

    def step() -> None:
        nonlocal k, state
        k += 1
        state = m.cycle(move(k))

    res.periods = _until(lambda: len(m.drive_emcy(since, 0x8130)) == len(DRIVES), step, "EMCY 0x8130")
    res.latency_ms = (time.monotonic() - t0) * 1e3
    res.periods += _until(lambda: all(sw & 0x4F == 0x40 for sw, _ in state.values()), step, "quick stop")
    res.states = {n: state[n][0] for n in DRIVES}
    res.emcy = m.drive_emcy(since, 0x8130)
    m.after_reaction(res, step)
    res.nmt = m.nmt_states()
    res.objects = m.errors()
    return res


def nmt_stop(m: FaultMaster) -> FaultResult:
    """NMT STOP of every drive mid-motion; the default reaction 0x6007 = 1 (Fault).  In STOPPED no
    EMCY and no SDO (CiA 301); the fault is read after ENTER PRE-OPERATIONAL."""
    m.fresh()
    _for_every_drive(m, (0x1017, 0, "H", HEARTBEAT_MS))
    here = m.enable_here()
    move = m.sway(here)
    for k in range(100):
        m.cycle(move(k))
    since, res = len(m.emcy), FaultResult()
    for node in DRIVES:
        m.drives[node].nmt.send_command(0x02)
    res.nmt = m.nmt_states("STOPPED")
    m.after_reaction(res, m.sync_only)
    res.emcy = m.drive_emcy(since, 0x8100)  # none: STOPPED
    for node in DRIVES:
        m.drives[node].nmt.send_command(0x80)
    res.extra["nmt_after"] = m.nmt_states("PRE-OPERATIONAL")
    res.states = {n: m.drive_u(n, 0x6041, 0, "H") for n in DRIVES}
    res.objects = m.errors()
    return res


def rpdo_stop(m: FaultMaster) -> FaultResult:
    """The master's RPDOs stop while its SYNCs go on; RPDO1's deadline 0x1400:5 =
    :data:`RPDO_DEADLINE_MS` counts control periods; the reaction: 0x6007 = 1 (Fault), 0x1029:1 = 0
    (to PRE-OPERATIONAL).  ``periods``: from the first SYNC without RPDO to the first period the
    robot stood braked."""
    m.fresh()
    _for_every_drive(m, (0x1017, 0, "H", HEARTBEAT_MS))
    here = m.enable_here(lambda: _for_every_drive(m, (0x1400, 5, "H", RPDO_DEADLINE_MS)))
    move = m.sway(here)
    for k in range(100):
        m.cycle(move(k))
    t0, since, res = time.monotonic(), len(m.emcy), FaultResult()
    m.sync_only()
    res.periods = 1 + _until(lambda: m.brakes() == 0xF, m.sync_only, "torque-free after the RPDO deadline")
    res.latency_ms = (time.monotonic() - t0) * 1e3
    m.after_reaction(res, m.sync_only)
    res.emcy = m.drive_emcy(since, 0x8250)
    res.nmt = m.nmt_states()
    res.states = {n: m.drive_u(n, 0x6041, 0, "H") for n in DRIVES}
    res.objects = m.errors()
    return res


def sync_stop(m: FaultMaster) -> FaultResult:
    """The master's SYNCs (and RPDOs) stop mid-motion; 0x1006 = :data:`SYNC_PERIOD_US` (lost after
    1.5 periods, on the monotonic clock); the reaction: 0x6007 = 2 (Disable voltage), 0x1029:1 = 1
    (NMT unchanged).  The master then steps on: the robot stands braked."""
    m.fresh()
    _for_every_drive(
        m, (0x1006, 0, "I", SYNC_PERIOD_US), (0x6007, 0, "h", 2), (0x1029, 1, "B", 1), (0x1017, 0, "H", HEARTBEAT_MS)
    )
    here = m.enable_here()
    move = m.sway(here)
    last: dict[int, tuple[int, int]] = {}
    for k in range(100):
        last = move(k)
        m.cycle(last)
    t0, since, res = time.monotonic(), len(m.emcy), FaultResult()
    with m._cond:
        if not m._cond.wait_for(lambda: len(m.drive_emcy(since, 0x8100)) == len(DRIVES), WAIT_S):
            raise TimeoutError("no EMCY 0x8100 of every drive")
    res.latency_ms = (time.monotonic() - t0) * 1e3
    res.emcy = m.drive_emcy(since, 0x8100)
    res.states = {n: m.drive_u(n, 0x6041, 0, "H") for n in DRIVES}
    tpdos: dict[int, tuple[int, int]] = {}

    def step() -> None:
        nonlocal tpdos
        tpdos = m.cycle(last)  # the master is back: SYNCs and RPDOs, TPDOs (NMT still OPERATIONAL)

    m.after_reaction(res, step)
    res.extra["tpdo_states"] = {n: tpdos[n][0] for n in DRIVES}
    res.nmt = m.nmt_states()
    res.objects = m.errors()
    return res


def end_stop(m: FaultMaster) -> FaultResult:
    """The master drives the tool straight down until the lower arms pass their 80° end stop: the
    robot's fault (one EMCY 0xFF10 of the plant node, every joint braked); the drives that go on
    pushing leave their following-error window 0x6065 (set to 0.06 rad here): EMCY 0x8611, Fault."""
    m.fresh()
    here = m.enable_here(lambda: _for_every_drive(m, (0x6065, 0, "I", 100_000)))
    x0 = np.array([m.u(0x2452, j, signed=True) * 1e-6 for j in (1, 2, 3, 4)])
    z = np.linspace(x0[2], -0.87, 460)
    x = np.repeat(x0[None, :], len(z), axis=0)
    x[:, 2] = z
    dq = np.rint((inverse_kinematics(x) - inverse_kinematics(x0)) / units.RAD_PER_COUNT).astype(np.int64)
    since, res = len(m.emcy), FaultResult()
    k = 0

    def step() -> None:
        nonlocal k
        row = dq[min(k, len(dq) - 1)]
        k += 1
        m.cycle({n: (0x0F, here[n] + int(row[n - 1])) for n in DRIVES})

    def robot_emcy() -> list[bytes]:
        with m._cond:
            return [data for cob, data in m.emcy[since:] if cob == 0x080 + PLANT_ID]

    _until(lambda: bool(robot_emcy()), step, "the robot's EMCY")
    res.periods = k  # from the start of the move: the fault is in the period that reaches the stop
    res.extra["fault"] = {"code": m.u(0x2450, 9), "joint": m.u(0x2450, 10), "period": m.u(0x2450, 11)}
    _until(lambda: bool(m.drive_emcy(since, 0x8611)), step, "a following error")
    m.after_reaction(res, step)
    res.robot_emcy = robot_emcy()
    res.emcy = m.drive_emcy(since, 0x8611)
    res.objects = {n: m.errors()[n] for n in res.emcy}
    res.states = {n: m.drive_u(n, 0x6041, 0, "H") for n in DRIVES}
    return res


#: name → scenario
SCENARIOS: dict[str, Callable[[FaultMaster], FaultResult]] = {
    "heartbeat-lost": heartbeat_lost,
    "nmt-stop": nmt_stop,
    "rpdo-stop": rpdo_stop,
    "sync-stop": sync_stop,
    "end-stop": end_stop,
}

"""Tests of plant/plant_node.py (the plant as the test-bench CANopen node), bus/plant.eds,
host/nodes/plant_client.py and host/nodes/sdo_access.py: objects over SDO with the canopen
library, the trial protocol against scripted drives (faults: timeout, duplicate/stale/early
frames, plant error, abort), and the rig on python-can ``virtual`` buses — four DriveNode
threads, the PlantNode thread, the host through canopen RemoteNodes — bit-identical to the
in-process bench.

Synchronisation is by events only (frames, states, the scripted drives' hold), never by sleeping;
timeouts are checked on a manual node clock, never against the wall clock.  The tick rate over
the hub with real processes is a benchmark: benchmarks/plant_node_speed.py.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import struct
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np
import pytest
from canopen.objectdictionary import ODRecord, ODVariable, import_od
from canopen.objectdictionary import datatypes as dt
from clock_util import ManualClock, wait_for
from hub_util import serving
from hypothesis import given, settings
from hypothesis import strategies as st
from robot_util import NodeThread
from short_move import TS_S, configure_drives, short_reference

from bus import io_frames, units
from bus.cia301.emcy import decode_emcy
from bus.errors import AbortCode, SdoAbort
from bus.plant_objects import (
    PLANT_EDS_PATH,
    ConfigSub,
    CounterSub,
    InitialStateError,
    PlantFault,
    PlantObj,
    PlantStatus,
    PlantTrialSub,
    pack_initial_state,
    unpack_initial_state,
)
from bus.transports.hub.core import HUB_CORE_ENV, core_built
from bus.transports.hub.server import HubServer
from host.nodes.plant_client import (
    PlantClient,
    PlantInputError,
    PlantTimeoutError,
    PlantTrialFault,
)
from host.nodes.sdo_access import SdoAccess, SdoTransportError
from plant.plant_node import PlantNode

ROOT = Path(__file__).resolve().parents[1]
DRIVE_EDS = ROOT / "bus" / "drive.eds"
PLANT_ID = 32

_counter = itertools.count()

pytestmark = pytest.mark.usefixtures("no_leaked_virtual_channels")


# ---------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------


class FakePlant:
    """Deterministic stand-in: counts start at round(1000·q0) and move by 1 + τ_j per step."""

    def __init__(self, ts_s: float, substeps: int) -> None:
        self.ts_s, self.substeps = ts_s, substeps
        self.steps: list[tuple[list[int], list[float]]] = []
        self.resets: list[tuple[list[float], list[float]]] = []
        self.fail_at: int | None = None
        self.counts = np.zeros(4, dtype=np.int64)

    def reset(self, q0: np.ndarray, qd0: np.ndarray) -> None:
        self.resets.append((list(q0), list(qd0)))
        self.steps = []
        self.counts = np.rint(np.asarray(q0) * 1000).astype(np.int64)

    def encoder_counts(self) -> np.ndarray:
        return self.counts.copy()

    def step(self, torque_units: np.ndarray, disturbance_nm: np.ndarray) -> None:
        if self.fail_at is not None and len(self.steps) == self.fail_at:
            raise RuntimeError("simulated FK failure")
        self.steps.append((torque_units.tolist(), disturbance_nm.tolist()))
        self.counts += 1 + torque_units


class PlantBox:
    """plant_factory recording every plant it built."""

    def __init__(self) -> None:
        self.built: list[FakePlant] = []

    def __call__(self, ts_s: float, substeps: int) -> FakePlant:
        p = FakePlant(ts_s, substeps)
        self.built.append(p)
        return p


def fake_disturbance(kind: str, seed: int, trial: int, n_ticks: int, ts_s: float) -> np.ndarray:
    code = ("none", "repetitive", "nonrepetitive", "both").index(kind)
    base = code * 1000.0 + seed * 100.0 + trial * 10.0
    return base + np.arange(n_ticks * 4, dtype=np.float64).reshape(n_ticks, 4) * ts_s


Policy = Callable[[int, int, int, int], list[tuple[int, int]]]


def honest(joint: int, n: int, wire: int, count: int) -> list[tuple[int, int]]:
    """One torque frame per encoder frame: (wire tick, torque = joint − count mod 7)."""
    return [(wire, joint - (count % 7))]


class ScriptedDrives:
    """The four drives as one thread on the io bus, answering by ``policy``.

    :meth:`hold_at` makes them answer only the ticks before a given one: the frames of later
    ticks wait (in order) until :meth:`hold_at` allows them, so a test decides exactly how far
    a trial gets."""

    def __init__(self, io_channel: str, policy: Policy = honest, bus: can.BusABC | None = None) -> None:
        self.bus = can.Bus(interface="virtual", channel=io_channel) if bus is None else bus
        self.policy = policy
        self.controls: list[io_frames.ControlFrame] = []
        self.encoders: list[io_frames.EncoderFrame] = []
        self._origin = 0
        self._hold_at: int | None = None
        self._allowed = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def hold_at(self, tick: int | None) -> None:
        """Answer ticks n < ``tick`` of a trial only (None: every tick)."""
        with self._allowed:
            self._hold_at = tick
            self._allowed.notify_all()

    def _may_answer(self, n: int) -> bool:
        """Wait until tick ``n`` may be answered; False if closing."""
        with self._allowed:
            self._allowed.wait_for(lambda: self._stop.is_set() or self._hold_at is None or n < self._hold_at)
            return not self._stop.is_set()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(timeout=0.01)
            if msg is None:
                continue
            frame = io_frames.decode_io(msg)
            if isinstance(frame, io_frames.ControlFrame):
                self.controls.append(frame)
                if frame.command == io_frames.IoControlCommand.TRIAL_START:
                    self._origin = frame.tick
            elif isinstance(frame, io_frames.EncoderFrame):
                self.encoders.append(frame)
                n = (frame.tick - self._origin) & io_frames.TICK_MASK
                if not self._may_answer(n):
                    return
                for wire, torque in self.policy(frame.joint, n, frame.tick, frame.count):
                    self.bus.send(io_frames.encode_torque(frame.joint, wire, torque, io_frames.TorqueStatus.ENABLED))

    def close(self) -> None:
        self._stop.set()
        with self._allowed:
            self._allowed.notify_all()
        self._thread.join(timeout=2.0)
        assert not self._thread.is_alive()
        self.bus.shutdown()


class Host:
    """canopen Network on a virtual fieldbus channel, EMCY and heartbeat capture."""

    def __init__(self, fb_channel: str, interface: str = "virtual") -> None:
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.02
        self.network.connect(interface=interface, channel=fb_channel)
        self.emcy: list[tuple[int, bytes]] = []
        self.heartbeats: list[tuple[int, int]] = []
        for node in (1, 2, 3, 4, PLANT_ID):
            self.network.subscribe(0x080 + node, lambda cob, data, _t: self.emcy.append((cob, bytes(data))))
            self.network.subscribe(0x700 + node, lambda cob, data, _t: self.heartbeats.append((cob, data[0])))

    def node(self, node_id: int, eds: Path) -> canopen.RemoteNode:
        remote = canopen.RemoteNode(node_id, str(eds))
        self.network.add_node(remote)
        return remote

    def close(self) -> None:
        self.network.disconnect()


class PlantRig:
    """PlantNode (fake plant) in a thread + canopen host + scripted drives, on python-can
    ``virtual`` buses or on a hub of this process (``hub``: :data:`TRANSPORTS`; the plant reads a
    trial's torque frames in C where the environment lets the hub client, ``ILCRIG_HUB_CORE``)."""

    def __init__(
        self,
        policy: Policy = honest,
        tick_timeout_s: float = 2.0,
        first_tick_timeout_s: float | None = None,
        transport: str = "virtual",
    ) -> None:
        k = next(_counter)
        self.fb_channel, self.io_channel = f"bench-fb-{k}", f"bench-io-{k}"
        self.plants = PlantBox()
        self._hub: contextlib.ExitStack | None = None
        interface = "virtual"
        if transport != "virtual":
            self._hub = contextlib.ExitStack()
            folder = Path(self._hub.enter_context(tempfile.TemporaryDirectory(prefix="plant-rig-")))
            server = self._hub.enter_context(serving(HubServer([f"unix:{folder}/hub.sock"])))
            address = server.addresses[0]
            self.fb_channel, self.io_channel, interface = f"{address}#fb", f"{address}#io", "ilcrig_hub"
        fb = can.Bus(interface=interface, channel=self.fb_channel)
        io = can.Bus(interface=interface, channel=self.io_channel)
        self.bench = PlantNode(
            fb,
            io,
            plant_factory=self.plants,
            disturbance_fn=fake_disturbance,
            tick_timeout_s=tick_timeout_s,
            first_tick_timeout_s=first_tick_timeout_s,
        )
        self.host = Host(self.fb_channel, interface)
        self.drives = ScriptedDrives(self.io_channel, policy, can.Bus(interface=interface, channel=self.io_channel))
        self.remote = self.host.node(PLANT_ID, PLANT_EDS_PATH)
        self.access = SdoAccess(self.remote)
        self.client = PlantClient(self.access)
        self.node = NodeThread(self.bench, [fb, io])

    def close(self) -> None:
        self.node.close()
        self.drives.close()
        self.host.close()
        if self._hub is not None:
            self._hub.close()


#: the plant's transports in the trial tests: python-can's virtual bus; the hub, its client
#: reading the trial's torque frames in C (``hub-c``, where the C core is built) or in Python
TRANSPORTS = ["virtual", "hub-c", "hub-python"]


@pytest.fixture(params=TRANSPORTS)
def transport(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Each transport of :data:`TRANSPORTS` (``ILCRIG_HUB_CORE`` set for the hub's)."""
    name = str(request.param)
    if name == "hub-c" and not core_built():
        pytest.skip("the hub's C core is not built here (no C compiler at install)")
    if name != "virtual":
        monkeypatch.setenv(HUB_CORE_ENV, name.removeprefix("hub-"))
    return name


@pytest.fixture
def rig(transport: str) -> Iterator[PlantRig]:
    r = PlantRig(transport=transport)
    try:
        yield r
    finally:
        r.close()


Q0 = np.array([0.5, 0.25, -0.125, 1.0])
QD0 = np.array([0.0, 0.1, 0.2, 0.30000000000000004])


def request_paced_trial(bench: PlantNode, n_ticks: int) -> None:
    """Boot ``bench``, configure pacing and a trial of ``n_ticks`` from (Q0, QD0) as the host
    would, and command its start (the bench not stepped yet)."""
    bench.start()
    bench.write_object(PlantObj.CONFIG, ConfigSub.PACING, b"\x01")
    bench.write_object(PlantObj.INITIAL_STATE, 0, pack_initial_state(Q0, QD0))
    bench.write_object(PlantObj.TRIAL, PlantTrialSub.N_TICKS, struct.pack("<I", n_ticks))
    bench.write_object(PlantObj.TRIAL, PlantTrialSub.COMMAND, b"\x01")


# ---------------------------------------------------------------------------------------
# EDS and object encodings
# ---------------------------------------------------------------------------------------


def test_eds_loads_with_import_od_and_matches_the_constants() -> None:
    od = import_od(str(PLANT_EDS_PATH), PLANT_ID)
    assert od[0x1018][4].default == PLANT_ID  # $NODEID serial
    assert od[0x1014].default == 0x80 + PLANT_ID
    assert od[0x1017].data_type == dt.UNSIGNED16
    expected = {
        (PlantObj.CONFIG, ConfigSub.CONTROL_PERIOD_US): (dt.UNSIGNED32, "rw", 1000),
        (PlantObj.CONFIG, ConfigSub.SUBSTEPS): (dt.UNSIGNED16, "rw", 4),
        (PlantObj.CONFIG, ConfigSub.DISTURBANCE): (dt.UNSIGNED8, "rw", 0),
        (PlantObj.CONFIG, ConfigSub.SEED): (dt.UNSIGNED32, "rw", 0),
        (PlantObj.TRIAL, PlantTrialSub.TRIAL_INDEX): (dt.UNSIGNED32, "rw", 0),
        (PlantObj.TRIAL, PlantTrialSub.N_TICKS): (dt.UNSIGNED32, "rw", 1),
        (PlantObj.TRIAL, PlantTrialSub.COMMAND): (dt.UNSIGNED8, "wo", 0),
        (PlantObj.TRIAL, PlantTrialSub.STATUS): (dt.UNSIGNED8, "ro", 0),
        (PlantObj.TRIAL, PlantTrialSub.TICKS_DONE): (dt.UNSIGNED32, "ro", 0),
        (PlantObj.TRIAL, PlantTrialSub.FAULT_CODE): (dt.UNSIGNED8, "ro", 0),
        (PlantObj.TRIAL, PlantTrialSub.FAULT_TICK): (dt.UNSIGNED32, "ro", 0),
        (PlantObj.TRIAL, PlantTrialSub.FAULT_NODE): (dt.UNSIGNED8, "ro", 0),
    }
    expected |= {(PlantObj.COUNTERS, s): (dt.UNSIGNED32, "ro", 0) for s in CounterSub}
    for (index, sub), (dtype, access, default) in expected.items():
        rec = od[int(index)]
        assert isinstance(rec, ODRecord)
        var = rec[int(sub)]
        assert (var.data_type, var.access_type, var.default) == (dtype, access, default), (hex(index), sub)
    state = od[int(PlantObj.INITIAL_STATE)]
    assert isinstance(state, ODVariable) and state.data_type == dt.DOMAIN


def test_initial_state_packing_is_exact() -> None:
    q0 = np.array([0.1 + 0.2, -0.0, 5e-324, -1.7976931348623157e308])
    qd0 = np.array([1 / 3, -2 / 3, 1e-300, 3.0])
    data = pack_initial_state(q0, qd0)
    assert len(data) == 64 and data[:8] == struct.pack("<d", 0.1 + 0.2)
    q, qd = unpack_initial_state(data)
    assert q.tobytes() == q0.tobytes() and qd.tobytes() == qd0.tobytes()
    with pytest.raises(InitialStateError, match="4 values"):
        pack_initial_state([0.0] * 3, [0.0] * 4)
    with pytest.raises(InitialStateError, match="finite"):
        pack_initial_state([0.0, math.nan, 0.0, 0.0], [0.0] * 4)
    with pytest.raises(InitialStateError, match="64 bytes"):
        unpack_initial_state(b"\x00" * 63)


def test_plant_node_modules_respect_the_dependency_direction() -> None:
    """bus never imports plant/firmware/host; the plant node (plant/plant_node.py and its parts
    plant/plant_node_*.py) never imports firmware/host; the plant client imports only bus (its
    ObjectAccess protocol is bus.cia301.sdo's)."""
    import ast

    def imported(rel: str) -> set[str]:
        tree = ast.parse((ROOT / rel).read_text())
        mods: set[str] = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                mods |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module:
                mods.add(node.module)
        return mods

    for rel in ("bus/cia301/slave.py", "bus/cia301/object_store.py", "bus/plant_objects.py"):
        assert not {m.split(".")[0] for m in imported(rel)} & {"plant", "firmware_model", "host"}, rel
    node_parts = sorted((ROOT / "plant").glob("plant_node*.py"))
    assert ROOT / "plant" / "plant_node.py" in node_parts
    for path in node_parts:
        assert not {m.split(".")[0] for m in imported(str(path.relative_to(ROOT)))} & {"firmware_model", "host"}, path
    mods = imported("host/nodes/plant_client.py")
    assert {m.split(".")[0] for m in mods} <= {
        "__future__",
        "collections",
        "logging",
        "struct",
        "time",
        "dataclasses",
        "typing",
        "numpy",
        "bus",
        "host",
    }
    assert {m for m in mods if m.startswith("host")} == set()


_finite = st.floats(allow_nan=False, allow_infinity=False)


@settings(max_examples=200, deadline=None)
@given(st.lists(_finite, min_size=8, max_size=8))
def test_initial_state_round_trip_property(vals: list[float]) -> None:
    q0, qd0 = np.array(vals[:4]), np.array(vals[4:])
    q, qd = unpack_initial_state(pack_initial_state(q0, qd0))
    assert q.tobytes() == q0.tobytes() and qd.tobytes() == qd0.tobytes()


# ---------------------------------------------------------------------------------------
# objects over SDO (canopen client)
# ---------------------------------------------------------------------------------------


def test_objects_over_sdo(rig: PlantRig) -> None:
    remote, client, access = rig.remote, rig.client, rig.access
    assert wait_for(lambda: (0x700 + PLANT_ID, 0x00) in rig.host.heartbeats)  # boot-up
    assert remote.sdo[0x1018][2].raw == 0xBE4C
    assert remote.sdo[0x1018][4].raw == PLANT_ID
    assert remote.sdo[0x1008].raw == "ilcrig plant node"
    built = (1.0, 1.0, 1.0, 1.0)
    assert client.configuration() == {"ts_s": 0.001, "substeps": 4, "disturbance": "none", "seed": 0, "plant_scales": built}
    client.configure(0.0005, 8, "both", 4_000_000_000, plant_scales=(1.1, 0.9, 0.0, 2.5))
    assert client.configuration() == {
        "ts_s": 0.0005,
        "substeps": 8,
        "disturbance": "both",
        "seed": 4_000_000_000,
        "plant_scales": (1.1, 0.9, 0.0, 2.5),
    }
    assert remote.sdo[0x2400][3].raw == 3 and remote.sdo[0x2400][6].raw == 1.1
    # the plant-uncertainty factors: finite, inertia and mass > 0
    with pytest.raises(SdoAbort) as err:
        access.write_object(PlantObj.CONFIG, ConfigSub.MASS_SCALE, struct.pack("<d", 0.0))
    assert err.value.code == AbortCode.VALUE_RANGE
    with pytest.raises(SdoAbort) as err:
        access.write_object(PlantObj.CONFIG, ConfigSub.FRICTION_SCALE, struct.pack("<d", float("nan")))
    assert err.value.code == AbortCode.VALUE_RANGE
    with pytest.raises(PlantInputError, match="payload_scale must be >= 0"):
        client.configure(0.0005, 8, "both", 0, plant_scales=(1.0, 1.0, 1.0, -1.0))
    # EDS limits, lengths and access enforced by the node, mapped to SdoAbort by the adapter
    for sub_index, data, code in (
        ((PlantObj.CONFIG, ConfigSub.DISTURBANCE), b"\x04", AbortCode.VALUE_TOO_HIGH),
        ((PlantObj.CONFIG, ConfigSub.SUBSTEPS), b"\x00\x00", AbortCode.VALUE_TOO_LOW),
        ((PlantObj.CONFIG, ConfigSub.CONTROL_PERIOD_US), b"\x01\x00", AbortCode.LENGTH_MISMATCH),
        ((PlantObj.TRIAL, PlantTrialSub.STATUS), b"\x01", AbortCode.READ_ONLY),
    ):
        with pytest.raises(SdoAbort) as err:
            access.write_object(*sub_index, data)
        assert err.value.code == code
    with pytest.raises(SdoAbort) as err:
        access.read_object(PlantObj.TRIAL, PlantTrialSub.COMMAND)
    assert err.value.code == AbortCode.WRITE_ONLY
    with pytest.raises(SdoAbort) as err:
        access.read_object(0x2499, 0)
    assert err.value.code == AbortCode.NO_OBJECT
    # start before any initial state: refused
    with pytest.raises(SdoAbort) as err:
        access.write_object(PlantObj.TRIAL, PlantTrialSub.COMMAND, b"\x01")
    assert err.value.code == AbortCode.DEVICE_STATE
    # initial state: exact bits through a segmented transfer; bad length / NaN refused
    q0 = np.array([0.1 + 0.2, -0.0, 5e-324, 1.0])
    state = pack_initial_state(q0, QD0)
    access.write_object(PlantObj.INITIAL_STATE, 0, state)
    assert access.read_object(PlantObj.INITIAL_STATE, 0) == state
    with pytest.raises(SdoAbort) as err:
        access.write_object(PlantObj.INITIAL_STATE, 0, state[:-1])
    assert err.value.code == AbortCode.LENGTH_MISMATCH
    with pytest.raises(SdoAbort) as err:
        access.write_object(PlantObj.INITIAL_STATE, 0, struct.pack("<8d", *([math.inf] + [0.0] * 7)))
    assert err.value.code == AbortCode.VALUE_RANGE
    assert access.read_object(PlantObj.INITIAL_STATE, 0) == state
    # host-side validation, before anything is sent
    with pytest.raises(PlantInputError, match="whole number of µs"):
        client.configure(0.0010000001, 4, "none", 0)
    with pytest.raises(PlantInputError, match="unknown disturbance"):
        client.configure(0.001, 4, "gusty", 0)
    with pytest.raises(PlantInputError, match="seed"):
        client.configure(0.001, 4, "none", -1)
    with pytest.raises(PlantInputError, match="4 values"):
        client.start_trial(0, 10, [0.0] * 3, [0.0] * 4)
    # heartbeat from 0x1017 and NMT
    remote.sdo[0x1017].raw = 20
    rig.host.network.nmt.send_command(0x01)
    assert wait_for(lambda: [s for c, s in rig.host.heartbeats if c == 0x700 + PLANT_ID].count(0x05) >= 2)


def test_sdo_access_maps_a_silent_node_to_a_transport_error(rig: PlantRig) -> None:
    ghost = rig.host.node(99, PLANT_EDS_PATH)
    ghost.sdo.RESPONSE_TIMEOUT = 0.05
    with pytest.raises(SdoTransportError, match="node 99: read 0x1018:1 failed"):
        SdoAccess(ghost).read_object(0x1018, 1)
    with pytest.raises(SdoTransportError, match="node 99: write"):
        SdoAccess(ghost).write_object(0x1017, 0, b"\x00\x00")


def test_an_interrupt_inside_a_block_download_stays_the_interrupt(rig: PlantRig, monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGINT (a KeyboardInterrupt) while a 64-byte object goes by SDO block download: the caller
    gets the interrupt, not the "Block download unsuccessful" canopen's stream raises as it is
    closed on the way out (a Ctrl-C read as an ``sdo_error`` fault); the node is sent an abort and
    serves the next transfer."""
    sdo = rig.remote.sdo
    real = sdo.send_request
    sent: list[bytes] = []

    def send(request: bytes) -> None:
        sent.append(bytes(request))
        if len(sent) == 2:  # the first segment of the first sub-block, after the initiation
            raise KeyboardInterrupt
        real(request)

    monkeypatch.setattr(sdo, "send_request", send)
    with pytest.raises(KeyboardInterrupt):
        rig.access.write_object(PlantObj.INITIAL_STATE, 0, pack_initial_state(Q0, QD0))
    assert sent[0][0] & 0xE0 == 0xC0  # block download initiate
    assert sent[-1][0] == 0x80  # the transfer aborted at the node
    monkeypatch.undo()
    q1 = np.array([0.25, -0.5, 0.125, 0.0])
    rig.access.write_object(PlantObj.INITIAL_STATE, 0, pack_initial_state(q1, QD0))
    q, qd = unpack_initial_state(rig.access.read_object(PlantObj.INITIAL_STATE, 0))
    np.testing.assert_array_equal(q, q1)
    np.testing.assert_array_equal(qd, QD0)


def test_nmt_reset_node_restores_defaults(rig: PlantRig) -> None:
    rig.client.configure(0.002, 2, "repetitive", 9)
    rig.host.heartbeats.clear()
    rig.remote.nmt.send_command(0x81)
    assert wait_for(lambda: (0x700 + PLANT_ID, 0x00) in rig.host.heartbeats)
    assert rig.client.configuration() == {
        "ts_s": 0.001,
        "substeps": 4,
        "disturbance": "none",
        "seed": 0,
        "plant_scales": (1.0, 1.0, 1.0, 1.0),
    }


# ---------------------------------------------------------------------------------------
# the trial protocol against scripted drives
# ---------------------------------------------------------------------------------------


def test_trial_protocol_frames_plant_and_counters(rig: PlantRig, transport: str) -> None:
    client = rig.client
    client.configure(0.002, 3, "nonrepetitive", 5)
    n = 12
    for trial in (4, 5):
        client.start_trial(trial, n, Q0, QD0)
        state = client.wait_trial(5.0)
        assert (state.status, state.ticks_done, state.fault) == (PlantStatus.DONE, n, PlantFault.NONE)
        plant = rig.plants.built[-1]
        assert (plant.ts_s, plant.substeps) == (0.002, 3)
        assert plant.resets[-1] == (Q0.tolist(), QD0.tolist())
        dist = fake_disturbance("nonrepetitive", 5, trial, n, 0.002)
        assert [d for _, d in plant.steps] == dist.tolist()
        # torques: joint − (count mod 7), count = the encoder count sent for that tick
        counts = np.rint(Q0 * 1000).astype(np.int64)
        for k, (tau, _) in enumerate(plant.steps):
            want = [j - int(counts[j] % 7) for j in range(4)]
            assert tau == want, k
            counts = counts + 1 + np.array(want)
    assert len(rig.plants.built) == 2  # start(): default config; then (2 ms, 3): kept for trial 5
    # io frames: TRIAL_START, 4 encoders per tick with consecutive wire ticks, TRIAL_STOP
    ctl = rig.drives.controls
    assert [(c.command, c.n_ticks) for c in ctl] == [(1, n), (2, n)] * 2
    assert ctl[0].tick == 0 and ctl[1].tick == n and ctl[2].tick == n + 1 and ctl[3].tick == 2 * n + 1
    enc = rig.drives.encoders
    assert len(enc) == 2 * 4 * n
    assert [e.tick for e in enc[: 4 * n : 4]] == list(range(n))
    assert [e.joint for e in enc[:4]] == [0, 1, 2, 3]
    assert enc[0].count == round(Q0[0] * 1000)
    c = client.counters()
    assert c["io_sent"] == 2 * (4 * n + 2) and c["io_received"] == 2 * 4 * n
    assert c["trials_done"] == 2 and c["tick_timeouts"] == 0 and c["last_trial_us"] > 0
    assert not rig.host.emcy
    if transport == "hub-c":  # read in C: every tick's torque frames after a wake-up that left the service nothing to do
        assert rig.bench.answered > 0
    else:
        assert rig.bench.answered == 0


def test_status_is_served_during_a_trial(transport: str) -> None:
    """The drives are held (no tick timeout can fire: 60 s), so the trial stands exactly where the
    test wants it while the status is polled."""
    rig = PlantRig(tick_timeout_s=60.0, transport=transport)
    try:
        rig.drives.hold_at(0)
        rig.client.start_trial(0, 100, Q0, QD0)
        seen = [rig.client.status() for _ in range(3)]
        assert [(s.status, s.ticks_done) for s in seen] == [(PlantStatus.RUNNING, 0)] * 3
        rig.drives.hold_at(40)
        assert wait_for(lambda: rig.client.status().ticks_done == 40)
        seen = [rig.client.status() for _ in range(3)]
        assert [(s.status, s.ticks_done) for s in seen] == [(PlantStatus.RUNNING, 40)] * 3
        with pytest.raises(SdoAbort) as err:  # no reconfiguration while running
            rig.access.write_object(PlantObj.CONFIG, ConfigSub.SEED, b"\x01\x00\x00\x00")
        assert err.value.code == AbortCode.DEVICE_STATE
        with pytest.raises(SdoAbort) as err:
            rig.access.write_object(PlantObj.TRIAL, PlantTrialSub.COMMAND, b"\x01")
        assert err.value.code == AbortCode.DEVICE_STATE
        assert rig.client.status() == seen[-1]  # refused writes changed nothing
        rig.drives.hold_at(None)
        assert rig.client.wait_trial(5.0).ticks_done == 100
    finally:
        rig.close()


def _emcy_of_plant(rig: PlantRig) -> list[tuple[int, int, bytes]]:
    out = []
    for cob, data in rig.host.emcy:
        if cob == 0x80 + PLANT_ID:
            m = decode_emcy(data)
            out.append((m.code, m.register, m.manufacturer))
    return out


def test_drive_that_stops_answering_is_a_timeout_fault_and_the_node_recovers() -> None:
    silent_from = {"tick": 5}

    def policy(joint: int, n: int, wire: int, count: int) -> list[tuple[int, int]]:
        if joint == 2 and n >= silent_from["tick"]:
            return []
        return honest(joint, n, wire, count)

    rig = PlantRig(policy, tick_timeout_s=0.2)
    try:
        rig.client.start_trial(0, 20, Q0, QD0)
        with pytest.raises(PlantTrialFault, match="drive 3 did not answer tick 5") as err:
            rig.client.wait_trial(5.0)
        state = err.value.state
        assert (state.status, state.fault, state.fault_tick, state.fault_node, state.ticks_done) == (
            PlantStatus.FAULT,
            PlantFault.TICK_TIMEOUT,
            5,
            3,
            5,
        )
        assert wait_for(lambda: bool(_emcy_of_plant(rig)))
        assert _emcy_of_plant(rig) == [(0x8100, 0x11, bytes([2, 3, 5, 0, 0]))]
        assert rig.remote.sdo[0x1001].raw == 0x11
        assert "drive 3 did not answer tick 5" in rig.bench.last_fault_message
        assert rig.client.counters()["tick_timeouts"] == 1
        assert wait_for(lambda: [c.command for c in rig.drives.controls] == [1, 2])
        assert rig.drives.controls[1].tick == 5
        # the node keeps running: the next trial completes (and clears the error register)
        silent_from["tick"] = 10**9
        rig.client.start_trial(1, 8, Q0, QD0)
        assert rig.client.wait_trial(5.0).status == PlantStatus.DONE
        assert rig.remote.sdo[0x1001].raw == 0
    finally:
        rig.close()


def test_tick_zero_gets_the_longer_first_tick_timeout() -> None:
    """Tick timeouts on a manual node clock, the node stepped by the test (no thread; a virtual
    bus delivers on send): tick 0 may take ``first_tick_timeout_s`` (0.4 s), a later tick only
    ``tick_timeout_s`` (0.05 s); a timeout falls due exactly at its deadline."""
    k = next(_counter)
    clock = ManualClock(1000.0)
    fb = can.Bus(interface="virtual", channel=f"bench-fb-{k}")
    io = can.Bus(interface="virtual", channel=f"bench-io-{k}")
    drives = can.Bus(interface="virtual", channel=f"bench-io-{k}")
    bench = PlantNode(
        fb,
        io,
        plant_factory=PlantBox(),
        disturbance_fn=fake_disturbance,
        tick_timeout_s=0.05,
        first_tick_timeout_s=0.4,
        clock=clock,
    )

    def start_trial(trial: int) -> None:
        bench.write_object(PlantObj.TRIAL, PlantTrialSub.TRIAL_INDEX, struct.pack("<I", trial))
        bench.write_object(PlantObj.TRIAL, PlantTrialSub.COMMAND, b"\x01")
        bench.step(0.0)  # the trial begins: TRIAL_START and the encoder frames of tick 0

    def answer(joints: set[int]) -> None:
        """Answer this tick's encoder frames for ``joints`` only, then let the node read them."""
        encoders = []
        while (msg := drives.recv(timeout=0)) is not None:
            frame = io_frames.decode_io(msg)
            if isinstance(frame, io_frames.EncoderFrame):
                encoders.append(frame)
        assert sorted(e.joint for e in encoders) == [0, 1, 2, 3]
        for e in encoders:
            if e.joint in joints:
                drives.send(io_frames.encode_torque(e.joint, e.tick, 0, io_frames.TorqueStatus.ENABLED))
        bench.step(0.0)

    def status_at(t: float) -> PlantStatus:
        clock.now = t
        bench.step(0.0)
        return bench.status

    try:
        bench.start()
        bench.write_object(PlantObj.INITIAL_STATE, 0, pack_initial_state(Q0, QD0))
        bench.write_object(PlantObj.TRIAL, PlantTrialSub.N_TICKS, struct.pack("<I", 5))
        # trial 0: drive 1 never answers tick 0 (encoders sent at 1000.0)
        start_trial(0)
        answer({1, 2, 3})
        assert [status_at(1000.0 + dt) for dt in (0.05, 0.2, 0.399)] == [PlantStatus.RUNNING] * 3
        assert (bench.ticks_done, bench.tick_timeouts) == (0, 0)
        assert status_at(1000.0 + 0.4) == PlantStatus.FAULT
        assert (bench.fault, bench.tick_timeouts) == (PlantFault.TICK_TIMEOUT, 1)
        assert bench.last_fault_message.startswith("drive 1 did not answer tick 0 within 0.4 s")
        # trial 1: tick 0 complete, drive 1 silent at tick 1 (encoders sent at 2000.0)
        clock.now = 2000.0
        start_trial(1)
        answer({0, 1, 2, 3})
        answer({1, 2, 3})
        assert status_at(2000.0 + 0.049) == PlantStatus.RUNNING
        assert bench.ticks_done == 1
        assert status_at(2000.0 + 0.05) == PlantStatus.FAULT
        assert (bench.fault, bench.tick_timeouts) == (PlantFault.TICK_TIMEOUT, 2)
        assert bench.last_fault_message.startswith("drive 1 did not answer tick 1 within 0.05 s")
    finally:
        for bus in (fb, io, drives):
            bus.shutdown()


@pytest.mark.parametrize("kind", ["duplicate", "stale", "early", "missing"])
def test_bad_torque_sequence_is_a_fault(kind: str, transport: str) -> None:
    def policy(joint: int, n: int, wire: int, count: int) -> list[tuple[int, int]]:
        frames = honest(joint, n, wire, count)
        if joint == 1 and n == 6:
            if kind == "duplicate":
                return frames + frames
            if kind == "stale":
                return [(wire - 3, 0)]
            if kind == "early":
                return frames + [(wire + 1, 0)]
            return [(wire + 1, 0)]  # the frame of tick 6 missing, tick 7 instead
        return frames

    rig = PlantRig(policy, transport=transport)
    try:
        rig.client.start_trial(0, 20, Q0, QD0)
        with pytest.raises(PlantTrialFault, match="drive 2 out of sequence at tick 6") as err:
            rig.client.wait_trial(5.0)
        assert (err.value.state.fault, err.value.state.fault_node) == (PlantFault.TICK_SEQUENCE, 2)
        words = {"duplicate": "duplicate", "stale": "stale", "early": "during tick 6", "missing": "missing"}
        assert words[kind] in rig.bench.last_fault_message
        assert wait_for(lambda: bool(_emcy_of_plant(rig)))
        assert _emcy_of_plant(rig)[0][:2] == (0x8200, 0x11)
        # the plant never integrated tick 6 with a wrong or missing torque
        assert len(rig.plants.built[-1].steps) <= 6 + (kind == "duplicate")
    finally:
        rig.close()


def test_plant_error_is_a_fault(rig: PlantRig) -> None:
    assert wait_for(lambda: bool(rig.plants.built))  # built at node start, kept for Ts = 1 ms
    rig.plants.built[-1].fail_at = 3
    rig.client.start_trial(0, 10, Q0, QD0)
    with pytest.raises(PlantTrialFault, match="plant error at tick 3") as err:
        rig.client.wait_trial(5.0)
    assert err.value.state.fault == PlantFault.PLANT
    assert "simulated FK failure" in rig.bench.last_fault_message
    assert wait_for(lambda: bool(_emcy_of_plant(rig)))
    assert _emcy_of_plant(rig)[0] == (0xFF00, 0x81, bytes([1, 0, 3, 0, 0]))


def test_abort_command_and_nmt_stop_end_a_trial() -> None:
    """The drives are held at tick 0 and no tick timeout can fire (60 s): each trial runs until
    the abort, the client's own timeout or the NMT stop ends it."""
    rig = PlantRig(tick_timeout_s=60.0)
    try:
        rig.drives.hold_at(0)
        rig.client.start_trial(0, 1000, Q0, QD0)
        rig.client.abort()
        with pytest.raises(PlantTrialFault, match="aborted"):
            rig.client.wait_trial(5.0)
        with pytest.raises(PlantTimeoutError, match="still running after 0.05 s"):
            rig.client.start_trial(1, 1000, Q0, QD0)
            rig.client.wait_trial(0.05)
        assert rig.client.status().fault == PlantFault.ABORTED  # the client aborted it
        rig.client.start_trial(2, 1000, Q0, QD0)
        rig.remote.nmt.send_command(0x02)  # stop
        assert wait_for(lambda: rig.bench.status == PlantStatus.FAULT)
        assert rig.bench.fault == PlantFault.ABORTED
        assert rig.bench.ticks_done == 0 and rig.bench.trials_done == 0
        rig.drives.hold_at(None)  # the drives read on: late answers (ignored), the control frames
        assert wait_for(lambda: [c.command for c in rig.drives.controls] == [1, 2] * 3)
        assert rig.bench.trials_done == 0
    finally:
        rig.close()


def test_run_plant_role_serves_until_stopped() -> None:
    """plant.plant_node.run_plant_role on a virtual transport: boots, runs a trial with the real
    plant (scripted zero-torque drives), stops on the event and closes its buses."""
    from bus.transports.config import virtual_transport
    from plant.kinematics import inverse_kinematics
    from plant.plant_node import run_plant_role

    transport = virtual_transport(f"plant-role-{next(_counter)}")
    host = Host(transport.fieldbus.channel)
    drives = ScriptedDrives(transport.io.channel, lambda j, n, wire, count: [(wire, 0)])
    stop = threading.Event()
    thread = threading.Thread(target=run_plant_role, args=(transport,), kwargs={"node_id": 33, "stop": stop}, daemon=True)
    try:
        boot: list[int] = []
        host.network.subscribe(0x700 + 33, lambda _c, data, _t: boot.append(data[0]))
        thread.start()
        assert wait_for(lambda: 0 in boot, 30.0)
        client = PlantClient(SdoAccess(host.node(33, PLANT_EDS_PATH)))
        client.start_trial(0, 20, inverse_kinematics(np.array([0.0, 0.0, -0.65, 0.0])), np.zeros(4))
        assert client.wait_trial(5.0).ticks_done == 20
        assert drives.encoders[-4].count != drives.encoders[0].count  # joint 1 sagged: a real plant
    finally:
        stop.set()
        thread.join(timeout=3.0)
        drives.close()
        host.close()
    assert not thread.is_alive()


# ---------------------------------------------------------------------------------------
# the rig on virtual buses vs the in-process bench: bit-identical traces
# ---------------------------------------------------------------------------------------


def _in_process_traces(n: int, trials: int, disturbance: str, seed: int) -> list[list[Any]]:
    from host.experiment.config import ExperimentConfig
    from host.sim.inprocess import InProcessBench

    q, qd, ff, q0 = short_reference(n)
    bench = InProcessBench(ExperimentConfig(ts_s=TS_S, substeps=4, disturbance=disturbance, seed=seed))
    bench.start()
    configure_drives(bench.drives, q, qd)
    out = []
    for k in range(trials):
        for j, d in enumerate(bench.drives):
            d.load_feedforward(ff[:, j])
            d.arm_trial()
        bench.run_trial(k, n, q[0].copy(), qd[0].copy())
        out.append([d.read_trace() for d in bench.drives])
    bench.close()
    return out


def test_rig_on_virtual_buses_is_bit_identical_to_in_process() -> None:
    from firmware_model.drive import Drive
    from firmware_model.drive_node import DriveNode
    from host.experiment.config import ExperimentConfig
    from host.nodes.drive_client import DriveClient
    from host.sim.inprocess import make_plant
    from plant.disturbance import disturbance_torque

    n, trials, disturbance, seed = 60, 2, "both", 11
    k = next(_counter)
    fb_ch, io_ch = f"rig-fb-{k}", f"rig-io-{k}"
    threads: list[NodeThread] = []
    host = Host(fb_ch)
    try:
        for node_id in (1, 2, 3, 4):
            fb = can.Bus(interface="virtual", channel=fb_ch)
            io = can.Bus(interface="virtual", channel=io_ch)
            threads.append(NodeThread(DriveNode(Drive(node_id), fb, io), [fb, io]))
        fb = can.Bus(interface="virtual", channel=fb_ch)
        io = can.Bus(interface="virtual", channel=io_ch)

        def factory(ts_s: float, substeps: int) -> Any:
            return make_plant(ExperimentConfig(ts_s=ts_s, substeps=substeps))

        bench_node = PlantNode(fb, io, plant_factory=factory, disturbance_fn=disturbance_torque)
        threads.append(NodeThread(bench_node, [fb, io]))
        drives = [DriveClient(SdoAccess(host.node(i, DRIVE_EDS)), i) for i in (1, 2, 3, 4)]
        bench = PlantClient(SdoAccess(host.node(PLANT_ID, PLANT_EDS_PATH)))
        assert wait_for(lambda: len({c for c, s in host.heartbeats if s == 0}) == 5, 5.0)  # 5 boot-ups
        host.network.nmt.send_command(0x01)  # all nodes operational
        q, qd, ff, _ = short_reference(n)
        configure_drives(drives, q, qd)
        bench.configure(TS_S, 4, disturbance, seed)
        rig_traces = []
        for trial in range(trials):
            for j, d in enumerate(drives):
                d.load_feedforward(ff[:, j])
                d.arm_trial()
            bench.start_trial(trial, n, q[0].copy(), qd[0].copy())
            assert bench.wait_trial(10.0).ticks_done == n
            rig_traces.append([d.read_trace() for d in drives])
        assert not [e for e in host.emcy if decode_emcy(e[1]).code != 0]
    finally:
        for t in threads:
            t.close()
        host.close()

    ref = _in_process_traces(n, trials, disturbance, seed)
    fields = ("position_counts", "velocity_counts_s", "torque_units", "torque_fb_units")
    for trial in range(trials):
        for j in range(4):
            for f in fields:
                a, b = getattr(rig_traces[trial][j], f), getattr(ref[trial][j], f)
                assert a.dtype == b.dtype and len(a) == n
                assert np.array_equal(a, b), (trial, j, f)
    # the trial did something, and the non-repetitive disturbance differs between trials
    pos = rig_traces[0][0].position_counts
    assert abs(int(pos[-1]) - int(pos[0])) > 0.02 / units.RAD_PER_COUNT
    assert not np.array_equal(rig_traces[0][0].torque_fb_units, rig_traces[1][0].torque_fb_units)


@pytest.mark.parametrize("expected", [None, "none", "nonrepetitive"])
def test_the_bench_pays_its_first_calls_at_boot_not_at_the_first_trial(expected: str | None) -> None:
    """start() builds the plant and computes a disturbance once (a non-repetitive one's first call
    imports scipy.signal, about a second), before the boot-up: a first trial's start then holds the
    select loop that answers SDO no longer than any other. The kind is the one the node was told
    to expect (``ilcrig run`` tells it the experiment's); by default every kind (``both``)."""
    k = next(_counter)
    calls: list[tuple[str, int, int, int, float]] = []
    built: list[tuple[float, int]] = []

    def disturbance(kind: str, seed: int, trial: int, n_ticks: int, ts_s: float) -> np.ndarray:
        calls.append((kind, seed, trial, n_ticks, ts_s))
        return fake_disturbance(kind, seed, trial, n_ticks, ts_s)

    def factory(ts_s: float, substeps: int) -> Any:
        built.append((ts_s, substeps))
        return PlantBox()(ts_s, substeps)

    fb = can.Bus(interface="virtual", channel=f"boot-fb-{k}")
    io = can.Bus(interface="virtual", channel=f"boot-io-{k}")
    host = can.Bus(interface="virtual", channel=f"boot-fb-{k}")
    try:
        told = {} if expected is None else {"disturbance": expected}
        bench = PlantNode(fb, io, plant_factory=factory, disturbance_fn=disturbance, **told)
        bench.start()
        assert built == [(0.001, 4)]
        assert calls == [(expected or "both", 0, 0, 2, 0.001)]
        boot = host.recv(timeout=0)
        assert boot is not None and (boot.arbitration_id, bytes(boot.data)) == (0x700 + PLANT_ID, b"\x00")
    finally:
        for bus in (fb, io, host):
            bus.shutdown()


@pytest.mark.multiprocess
def test_the_plant_node_benchmark_runs_its_trials() -> None:
    """benchmarks/plant_node_speed.py (hub, four drive processes and the plant process started as
    ``ilcrig run`` starts them) completes a short trial and prints its rates; it exits 0."""
    import re
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "plant_node_speed.py"
    proc = subprocess.run(
        [sys.executable, str(script), "--ticks", "200", "--trials", "1", "--floor-seconds", "0.3", "--pings", "50"],
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert re.search(r"^0\s+[\d,]+\s+[\d,]+\s+\d+\.\d\d\s+\d+\.\d\d\s+\d+\.\d\d$", proc.stdout, re.M), proc.stdout

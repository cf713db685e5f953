"""What a Rerun recording of ilcrig shows, as Arrow columns: the batches and the 3D robot scene.

This module owns the content side of the recordings (``host.analysis.recording`` owns the file
and its durability, ``host.analysis.live_view`` the live robot view): :class:`Batch` (component
columns of many entities sent as one record batch), colours, the robot's skeleton points by
forward kinematics (:func:`skeleton_points`, m), the robot of one trial (:func:`add_robot`) and
the static scene (:func:`add_static_scene`: base, motor axes, reference TCP path, series styles),
and :func:`rerun_environment` (what rerun's native library reads when it loads).
"""

from __future__ import annotations

import functools
import logging
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from host.planning.joint_reference import JointReference

logger = logging.getLogger(__name__)

__all__ = [
    "COLOR_FIRST",
    "COLOR_LAST",
    "N_JOINTS",
    "REFERENCE_GREY",
    "Batch",
    "add_robot",
    "add_static_scene",
    "components",
    "iteration_color",
    "reference_xyz",
    "rerun_environment",
    "rgba_u32",
    "skeleton_points",
]

N_JOINTS = 4
COLOR_FIRST = (255, 140, 0, 255)
COLOR_LAST = (30, 144, 255, 255)
REFERENCE_GREY = (150, 150, 150, 255)


def rgba_u32(c: Sequence[int]) -> int:
    r, g, b, a = (int(v) & 0xFF for v in c)
    return (r << 24) | (g << 16) | (b << 8) | a


def iteration_color(k: int, n_expected: int | None) -> tuple[int, int, int, int]:
    """Red (first trial) → blue (last expected trial); beyond the expected count: blue."""
    n = max(int(n_expected or 10), 2)
    f = min(max(k / (n - 1), 0.0), 1.0)
    a, b = np.array([220, 50, 47]), np.array([38, 139, 210])
    r, g, bl = (a + f * (b - a)).round().astype(int)
    return int(r), int(g), int(bl), 255


def _data_field(pa: Any, entity: str, descriptor: Any, dtype: Any) -> Any:
    """Arrow field of one component column of ``entity`` with the Rerun metadata that
    ``send_columns`` would attach (so ``Chunk.from_record_batch`` splits a batch per entity)."""
    return pa.field(
        f"{entity}:{descriptor.component}",
        dtype,
        metadata={
            "rerun:entity_path": entity,
            "rerun:kind": "data",
            "rerun:component": descriptor.component,
            "rerun:archetype": descriptor.archetype or "",
            "rerun:component_type": descriptor.component_type or "",
        },
    )


def rerun_environment() -> None:
    """Set what rerun's native library reads from the environment when it loads (a value the user
    set is kept): its allocator (mimalloc) reserves address space in arenas of
    ``MIMALLOC_ARENA_RESERVE``, 1 GiB by default and twice over in a process that records, i.e.
    2 GiB of virtual memory for a few MB of use; arenas of 64 MiB keep a long run inside a 2 GB
    address-space limit (``ulimit -v``) with room to spare.  pyarrow's default memory pool (its
    own mimalloc, which does not take that option) reserves an arena of 1 GiB at its first Arrow
    array; the recording's few MB of Arrow batches take the system allocator instead
    (``ARROW_DEFAULT_MEMORY_POOL``, read when the pool is first used).  Called before every
    ``import rerun`` and before the recording's first Arrow array."""
    os.environ.setdefault("MIMALLOC_ARENA_RESERVE", "64MiB")
    os.environ.setdefault("ARROW_DEFAULT_MEMORY_POOL", "system")


@functools.lru_cache(maxsize=1)
def components() -> dict[str, tuple[Any, Any]]:
    """Component name (``Archetype:field``) → (descriptor, Arrow type), taken once per process
    from rerun's own converters; the hand-built arrays below are cast to these types."""
    rerun_environment()
    import rerun as rr

    cols = [
        *rr.Scalars.columns(scalars=[0.0]),
        *rr.SeriesLines.columns(names=["x"], colors=[0]),
        *rr.SeriesPoints.columns(names=["x"], colors=[0], marker_sizes=[1.0]),
        *rr.Points3D.columns(positions=[[0.0, 0.0, 0.0]], radii=[1.0], colors=[0], labels=["x"]),
        *rr.LineStrips3D.columns(strips=[[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]], radii=[1.0], colors=[0]),
        *rr.TextDocument.columns(text=["x"], media_type=["text/markdown"]),
    ]
    return {c.component_descriptor().component: (c.component_descriptor(), c.as_arrow_array().type) for c in cols}


def _nested(pa: Any, xyz: np.ndarray, dtype: Any) -> Any:
    """Rows of (strips of) 3D points as an Arrow list array: ``xyz`` (R, P, 3) → R rows of P points,
    (R, S, P, 3) → R rows of S strips of P points."""
    arr = pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(xyz, dtype=np.float32).ravel()), 3)
    for size in reversed(xyz.shape[1:-1]):
        count = len(arr) // size
        arr = pa.ListArray.from_arrays(pa.array(np.arange(0, count * size + 1, size, dtype=np.int32)), arr)
    return arr.cast(dtype)


class Batch:
    """Component columns of many entities sharing one index (or static), sent as ONE record batch:
    one Python→Rust call instead of one per entity."""

    def __init__(self, pa: Any) -> None:
        self._pa = pa
        self.fields: list[Any] = []
        self.arrays: list[Any] = []

    def add(self, entity: str, columns: Any) -> None:
        """Add the columns of an ``rr.<Archetype>.columns(...)`` list (partitioned or not)."""
        for c in columns:
            arr = c.as_arrow_array()
            self.fields.append(_data_field(self._pa, entity, c.component_descriptor(), arr.type))
            self.arrays.append(arr)

    def put(self, entity: str, component: str, value: Any) -> None:
        """Add one column: ``value`` is an Arrow array, (R, [S,] P, 3) points, or a list of rows."""
        descriptor, dtype = components()[component]
        if isinstance(value, np.ndarray):
            value = _nested(self._pa, value, dtype)
        elif not isinstance(value, self._pa.Array):
            value = self._pa.array(value, dtype)
        self.add_array(entity, descriptor, value)

    def add_array(self, entity: str, descriptor: Any, array: Any) -> None:
        self.fields.append(_data_field(self._pa, entity, descriptor, array.type))
        self.arrays.append(array)

    def send(self, rec: Any, index_name: str | None = None, index_array: Any = None) -> None:
        pa = self._pa
        if not self.fields:
            return
        fields, arrays = list(self.fields), list(self.arrays)
        if index_name is not None:
            fields.insert(
                0,
                pa.field(
                    index_name,
                    index_array.type,
                    metadata={"rerun:index_name": index_name, "rerun:kind": "index", "rerun:is_sorted": "true"},
                ),
            )
            arrays.insert(0, index_array)
        rec.send_record_batch(pa.RecordBatch.from_arrays(arrays, schema=pa.schema(fields)), index=index_name)
        self.fields.clear()
        self.arrays.clear()


def add_static_scene(st: Batch, ref: JointReference | None, decimate: int) -> None:
    """The static 3D scene and series styles: the base with its motor axes, the reference TCP path,
    the metrics' names and colours (one colour per joint)."""
    from plant.params import Geometry

    g = Geometry()
    phi = np.asarray(g.azimuths_rad)
    e = np.stack([np.cos(phi), np.sin(phi), np.zeros(4)], axis=1)
    u_axis = np.stack([-np.sin(phi), np.cos(phi), np.zeros(4)], axis=1)
    A = g.R * e
    grey = rgba_u32((90, 90, 90, 255))
    st.put("/robot/base", "Points3D:positions", A[None])
    st.put("/robot/base", "Points3D:radii", [[0.012]])
    st.put("/robot/base", "Points3D:colors", [[grey]])
    st.put("/robot/base", "Points3D:labels", [[f"M{i + 1}" for i in range(4)]])
    st.put("/robot/base/motor_axes", "LineStrips3D:strips", np.stack([A - 0.04 * u_axis, A + 0.04 * u_axis], axis=1)[None])
    st.put("/robot/base/motor_axes", "LineStrips3D:radii", [[0.006]])
    st.put("/robot/base/motor_axes", "LineStrips3D:colors", [[grey]])
    if ref is not None:
        xyz = reference_xyz(ref, decimate)
        if xyz is not None:
            st.put("/robot/reference_path", "LineStrips3D:strips", xyz[None, None])
            st.put("/robot/reference_path", "LineStrips3D:radii", [[0.0015]])
            st.put("/robot/reference_path", "LineStrips3D:colors", [[rgba_u32(REFERENCE_GREY)]])
    for key, label in (("rmse_deg", "RMSE"), ("maxe_deg", "MaxE")):
        for j in range(N_JOINTS):
            c = rgba_u32(((228, 26, 28, 255), (55, 126, 184, 255), (77, 175, 74, 255), (152, 78, 163, 255))[j])
            name = f"{label} joint {j + 1} [deg]"
            ent = f"/metrics/{key}/joint{j + 1}"
            st.put(ent, "SeriesLines:names", [[name]])
            st.put(ent, "SeriesLines:colors", [[c]])
            st.put(ent, "SeriesPoints:names", [[name]])
            st.put(ent, "SeriesPoints:colors", [[c]])
            st.put(ent, "SeriesPoints:marker_sizes", [[4.0]])


def reference_xyz(ref: JointReference, decimate: int) -> np.ndarray | None:
    """The reference TCP path (M, 3), m: the task path, or the joints' by forward kinematics (every
    ``decimate``-th sample); None when the kinematics fail."""
    if ref.task is not None:
        return np.asarray(ref.task.X[:, :3], dtype=np.float64)
    from plant.kinematics import KinematicsError, forward_kinematics, task_from_subplatform

    try:
        return task_from_subplatform(forward_kinematics(ref.q[::decimate]))[:, :3]
    except KinematicsError as exc:
        logger.warning("recording: no reference path in 3D: %s", exc)
        return None


def add_robot(
    data: Batch,
    static: Batch,
    which: str,
    q: np.ndarray,
    y_guess: np.ndarray | None,
    color: tuple[int, int, int, int],
) -> None:
    """The robot skeleton at every (decimated) sample of one trial under ``/robot/{which}``."""
    from plant.kinematics import KinematicsError, forward_kinematics

    try:
        Y = forward_kinematics(q, y_guess)
    except KinematicsError as exc:
        logger.warning("recording: no 3D view of the %s trial: %s", which, exc)
        return
    pts = skeleton_points(q, Y)
    m = q.shape[0]
    base = f"/robot/{which}"
    arms = np.stack([pts["A"], pts["B"], pts["C"]], axis=2).reshape(m * 4, 3, 3)  # A_i → B_i → C_i
    C, pu, pl, tcp = pts["C"], pts["P_up"], pts["P_low"], pts["tcp"]
    upper = np.stack([C[:, 0], pu, C[:, 2], C[:, 2]], axis=1)  # (padded to 4 points)
    lower = np.stack([C[:, 1], pl, C[:, 3], C[:, 3]], axis=1)
    shaft = np.stack([pu, pl, tcp, tcp + 0.05 * pts["tool_dir"]], axis=1)  # screw shaft, tool blade at θ
    plat = np.stack([upper, lower, shaft], axis=1).reshape(m * 3, 4, 3)
    c = [[rgba_u32(color)]]
    data.put(f"{base}/arms", "LineStrips3D:strips", arms.reshape(m, 4, 3, 3))
    data.put(f"{base}/sub_platforms", "LineStrips3D:strips", plat.reshape(m, 3, 4, 3))
    data.put(f"{base}/tool", "Points3D:positions", tcp[:, None, :])
    for ent, radius in (("arms", 0.006), ("sub_platforms", 0.005), ("tcp_path", 0.001)):
        static.put(f"{base}/{ent}", "LineStrips3D:radii", [[radius]])
        static.put(f"{base}/{ent}", "LineStrips3D:colors", c)
    static.put(f"{base}/tcp_path", "LineStrips3D:strips", tcp[None, None])
    static.put(f"{base}/tool", "Points3D:radii", [[0.012]])
    static.put(f"{base}/tool", "Points3D:colors", c)


def skeleton_points(q: np.ndarray, Y: np.ndarray, geometry: Any | None = None) -> dict[str, np.ndarray]:
    """Points of the robot's skeleton (docs/robot-model.md §3.1), base frame, m.

    :param q: (M, 4) joint angles, rad.  :param Y: (M, 4) sub-platform coordinates (x, y, z_u, z_l).
    :returns: ``A`` (M, 4, 3) motor-axis points, ``B`` elbows, ``C`` ball-bar midpoints, ``P_up`` /
        ``P_low`` (M, 3) sub-platform centres, ``tcp`` (M, 3), ``tool_dir`` (M, 3) unit vector at θ.
    """
    from plant.kinematics import task_from_subplatform
    from plant.params import LIMB_ON_UPPER, Geometry

    g = geometry if geometry is not None else Geometry()
    q = np.asarray(q, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    m = q.shape[0]
    phi = np.asarray(g.azimuths_rad)
    e = np.stack([np.cos(phi), np.sin(phi), np.zeros(4)], axis=1)  # (4, 3)
    k = np.array([0.0, 0.0, 1.0])
    A = np.broadcast_to(g.R * e, (m, 4, 3))
    B = A + g.l_a * (np.cos(q)[..., None] * e - np.sin(q)[..., None] * k)
    p_up = np.stack([Y[:, 0], Y[:, 1], Y[:, 2]], axis=1)
    p_low = np.stack([Y[:, 0], Y[:, 1], Y[:, 3]], axis=1)
    centre = np.where(np.asarray(LIMB_ON_UPPER)[None, :, None], p_up[:, None, :], p_low[:, None, :])
    C = centre + g.r * e
    X = task_from_subplatform(Y, g)
    tcp = X[:, :3]
    tool_dir = np.stack([np.cos(X[:, 3]), np.sin(X[:, 3]), np.zeros(m)], axis=1)
    return {"A": np.array(A), "B": B, "C": C, "P_up": p_up, "P_low": p_low, "tcp": tcp, "tool_dir": tool_dir}

"""The layout of ``recording.rrd``: its entity paths (:data:`SERIES`) and the viewer's blueprint
(:func:`default_blueprint`, its per-joint tabs :func:`joint_grid`); rerun is imported lazily (inside the function).

Layout (entity paths; timelines ``trial_time`` = t_n = n·Ts as a duration, ``iteration`` = k):

* ``/joint{j}/reference``  q_d of joint j (1..4), deg — one series (the same in every trial)
* ``/joint{j}/actual/iter{k}``     measured q (encoder) in trial k, deg
* ``/joint{j}/error/iter{k}``      e = q_d − q, deg
* ``/joint{j}/torque_ff/iter{k}``  feed-forward u_k sent to the drive, N·m
* ``/joint{j}/torque_fb/iter{k}``  feedback torque recorded by the drive, N·m
  All on ``trial_time`` with N rows (one per tick), one entity per iteration; the static
  ``SeriesLines`` name it ``<quantity> iter k [unit]`` (colour red = first → blue = last
  planned trial; reference grey), so the iterations overlay as K lines under
  ``/joint{j}/<quantity>``.
* ``/metrics/rmse_deg/joint{j}``, ``/metrics/maxe_deg/joint{j}``: one row per trial on the
  ``iteration`` sequence timeline (the values of the summary, deg).
* ``/robot`` (``ViewCoordinates.RIGHT_HAND_Z_UP``, base frame, m): static ``/robot/base``
  (motor-axis points A_i), ``/robot/base/motor_axes``, ``/robot/reference_path`` (reference TCP
  path); ``/robot/first/...`` (trial 0) and ``/robot/last/...`` (the last completed trial: logged
  again after every trial, the newest rows win), on ``trial_time`` every ``decimate_3d``-th
  sample, by forward kinematics from the MEASURED joint angles: ``arms`` (4 strips A_i → elbow
  B_i → ball-bar midpoint C_i: inner then outer arm), ``sub_platforms`` (upper bar C_1–C_3,
  lower bar C_2–C_4, screw shaft down to the tool with a 5 cm blade along θ), ``tool`` (TCP
  point) and a static ``tcp_path``.
* ``/run_info``: static text (configuration and how to read the recording).

May import: :mod:`host.analysis.recording_scene`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from host.analysis.recording_scene import N_JOINTS, rerun_environment

__all__ = ["SERIES", "default_blueprint", "joint_grid"]


#: per-joint time-series quantities (entity name, unit)
SERIES: tuple[tuple[str, str], ...] = (
    ("reference", "deg"),
    ("actual", "deg"),
    ("error", "deg"),
    ("torque_ff", "N·m"),
    ("torque_fb", "N·m"),
)


def joint_grid(kind: str, contents: Sequence[str], unit: str) -> Any:
    """A tab of the viewer: per joint j one time-series view of ``/joint{j}/<content>`` for each of
    ``contents`` (entity paths below the joint), named ``joint j <kind> [<unit>]``."""
    import rerun.blueprint as rrb

    return rrb.Grid(
        *[
            rrb.TimeSeriesView(
                origin=f"/joint{j}", contents=[f"+ /joint{j}/{c}" for c in contents], name=f"joint {j} {kind} [{unit}]"
            )
            for j in range(1, N_JOINTS + 1)
        ],
        name=kind,
    )


def default_blueprint() -> Any:
    """The viewer layout: per-joint error / torque / position plots (tabs), the 3D robot, metrics."""
    rerun_environment()
    import rerun.blueprint as rrb

    def grid(kind: str, parts: Sequence[str], unit: str) -> Any:
        return joint_grid(kind, [f"{p}/**" for p in parts], unit)

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Tabs(
                grid("error", ["error"], "deg"),
                grid("torque", ["torque_ff", "torque_fb"], "N·m"),
                grid("position", ["reference", "actual"], "deg"),
            ),
            rrb.Vertical(
                rrb.Tabs(
                    rrb.Spatial3DView(origin="/robot", name="robot: first (orange) vs last (blue) trial"),
                    rrb.TextDocumentView(origin="/run_info", name="run info"),
                ),
                rrb.Horizontal(
                    rrb.TimeSeriesView(origin="/metrics/rmse_deg", name="RMSE per iteration [deg]"),
                    rrb.TimeSeriesView(origin="/metrics/maxe_deg", name="MaxE per iteration [deg]"),
                ),
                row_shares=[3, 2],
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="trial_time"),
        collapse_panels=False,
    )

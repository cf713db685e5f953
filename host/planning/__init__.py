"""host.planning: what the robot is asked to do.

Owns the pick-and-place paths (:mod:`host.planning.paths`, built-ins and TOML path files, an
example in ``path_files/``), the task trajectories (:mod:`host.planning.task_plan`: the trial plan on
the time grid and axis windows of :mod:`host.planning.journeys`, with the 4-5-6-7 and 5th-order laws of
:mod:`host.planning.motion_laws` or the jerk-limited profile of :mod:`host.planning.ruckig_adapter`),
their mapping to joint references by inverse kinematics (:mod:`host.planning.joint_reference`), the
feasibility check (:mod:`host.planning.feasibility`) and the planning errors
(:mod:`host.planning.planning_errors`).

May import: ``bus`` (errors) and ``plant`` (kinematics, nominal dynamics, limits).
"""

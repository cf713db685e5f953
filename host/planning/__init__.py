"""host.planning: what the robot is asked to do.

Owns the pick-and-place paths (:mod:`host.planning.paths`, built-ins and TOML path files, an
example in ``path_files/``), the task trajectories (Ruckig jerk-limited, 4-5-6-7 and 5th-order
laws), their mapping to joint references by inverse kinematics and the feasibility check
(:mod:`host.planning.trajectory`).

May import: ``bus`` (errors) and ``plant`` (kinematics, nominal dynamics, limits).
"""

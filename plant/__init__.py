"""plant: the simulated robot.

Owns the robot's kinematics (:mod:`plant.kinematics`: IK/FK, Jacobians), dynamics
(:mod:`plant.dynamics`: M, C q̇, G, inverse / forward dynamics), parameters (:mod:`plant.params`),
the true-plant effects and the RK4 integrator (:mod:`plant.simulator`), the per-trial disturbances
(:mod:`plant.disturbance`), the robot's holding brakes, mechanical limits and home pose
(:mod:`plant.mechanics`), its period trace file (:mod:`plant.trace`), the real-time tick schedule
(:mod:`plant.pacing`), the numba kernels
(:mod:`plant._kernels`), a kernel timing and drive-train load check (``python -m host.cli.selfcheck``, :mod:`plant.selfcheck`)
and the plant's CANopen node: :mod:`plant.plant_node` (``PlantNode`` and the ``ilcrig plant``
process entry) with its parts :mod:`plant.plant_node_trial` (trial protocol, lockstep tick master,
pacing), :mod:`plant.plant_node_model` (the plant and disturbance of a trial),
:mod:`plant.plant_node_status` (trial status, faults and EMCY, timing),
:mod:`plant.plant_node_robot` (the robot between trials: one period per SYNC, ``ilcrig robot``),
:mod:`plant.plant_node_robot_pacing` (its real-time schedule) and
:mod:`plant.plant_node_hooks` (object hooks).

May import: numpy, scipy, numba and the standard library only — except the plant node,
:mod:`plant.plant_node` and its parts ``plant/plant_node_*.py``, which also import ``bus`` (they
speak CAN).  Never ``host`` or ``firmware_model``.
"""

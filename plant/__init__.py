"""plant: the simulated robot.

Owns the robot's kinematics (:mod:`plant.kinematics`: IK/FK, Jacobians), dynamics
(:mod:`plant.dynamics`: M, C q̇, G, inverse / forward dynamics), parameters (:mod:`plant.params`),
the true-plant effects and the RK4 integrator (:mod:`plant.simulator`), the real-time tick schedule
(:mod:`plant.pacing`), the per-trial disturbances
(:mod:`plant.disturbance`), the numba kernels (:mod:`plant._kernels`), a kernel timing and drive-train load check
(:mod:`plant.selfcheck`, ``python -m plant.selfcheck``) and, in :mod:`plant.plant_node`, the plant's CANopen plant node and the
``ilcrig plant`` process entry.

May import: numpy, scipy, numba and the standard library only — except :mod:`plant.plant_node`, which
also imports ``bus`` (it speaks CAN).  Never ``host`` or ``firmware_model``.
"""

"""plant: the simulated robot (kinematics, dynamics, true-plant effects, disturbances,
integrator, encoder and torque interfaces).  Depends only on numpy, scipy and numba.

Modules: :mod:`plant.params` (geometry, mass models, true-plant config),
:mod:`plant.kinematics` (IK/FK, Jacobians), :mod:`plant.dynamics` (M, C q̇, G, inverse /
forward dynamics, energy), :mod:`plant.disturbance` (per-trial disturbance torques),
:mod:`plant.simulator` (:class:`~plant.simulator.Plant`), :mod:`plant.bench`
(``python -m plant.bench``: step timing and gate-path torque check).  The numba kernels live
in the private :mod:`plant._kernels`.
"""

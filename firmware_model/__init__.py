"""firmware_model: the servo drive's firmware.

Owns the fixed-point control loop (:mod:`firmware_model.control_law`), the CiA 402 state machine
(:mod:`firmware_model.cia402`), the drive's object dictionary, feed-forward table playback and
data recorder (:mod:`firmware_model.drive`), and the drive process on the bus
(:mod:`firmware_model.drive_node`, ``ilcrig drive``).

May import: ``bus`` and ``bus.cia301`` (the contract it shares with the host).  Never ``host`` or
``plant``: the drive knows the robot only through its encoder and its torque command.
"""

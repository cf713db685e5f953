"""bus: everything both ends of a CAN frame must agree on.

Owns the units on the wire (:mod:`bus.units`), the firmware's fixed-point formats
(:mod:`bus.fixedpoint`), the object indices of the drive (:mod:`bus.objects`, ``drive.eds``) and of
the plant node (:mod:`bus.plant_objects`, ``plant.eds``), the io-channel frames
(:mod:`bus.io_frames`), bus-load accounting (:mod:`bus.busload`), candump logs (:mod:`bus.canlog`)
and the shared errors (:mod:`bus.errors`).  Subpackages: :mod:`bus.cia301` (the hand-written
CANopen stack) and :mod:`bus.transports` (how channels are carried).

May import: python-can, canopen (EDS import only), numpy, and its own modules.  Never
``firmware_model``, ``host`` or ``plant``.
"""

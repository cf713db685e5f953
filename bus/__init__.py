"""bus: everything both ends of a CAN frame must agree on.

Owns the units on the wire (:mod:`bus.units`), the firmware's fixed-point formats
(:mod:`bus.fixedpoint`), the object indices of the drive (:mod:`bus.objects`, ``drive.eds``; a PIL target's
fault EMCY: :mod:`bus.pil_fault`) and of
the plant node (:mod:`bus.plant_objects`, ``plant.eds``), the CiA 301 PDO object indices
(:mod:`bus.pdo_objects`), the rig's cyclic PDO layout and bus fit (:mod:`bus.cyclic`), the DBC files
(:mod:`bus.dbc`), the io-channel frames (:mod:`bus.io_frames`), bus-load accounting
(:mod:`bus.busload`), frame classification and bit counting (:mod:`bus.traffic`), the optional
extras of a python-can bus (:mod:`bus.bus_features`), SocketCAN's error frame of lost frames
(:mod:`bus.can_errors`), cheap messages on the hot path
(:mod:`bus.fastmsg`), fine timer slack (:mod:`bus.timer_slack`), the lockstep processes' frozen heap
and the real-time diagnostic switch (:mod:`bus.lockstep_process`), candump logs (:mod:`bus.canlog`),
the SAFE-STATE log record (:mod:`bus.safe_state`), the shared errors (:mod:`bus.errors`), every
exit code (:mod:`bus.exit_codes`), atomic writes (:mod:`bus.atomic`) and the one spawn function
with its lifetime policy (:mod:`bus.processes`), a record's writer and whether it still runs
(:mod:`bus.process_identity`), the process at the other end of a Unix socket (:mod:`bus.peer`),
a process's wait for a CPU and the ledger of the heartbeat judges (:mod:`bus.run_queue`).
Subpackages: :mod:`bus.cia301` (the hand-written CANopen stack) and :mod:`bus.transports` (how
channels are carried).

May import: python-can, canopen (EDS import only), numpy, and its own modules.  Never
``firmware_model``, ``host`` or ``plant``.
"""

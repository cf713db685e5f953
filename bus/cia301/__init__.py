"""bus.cia301: the hand-written CANopen (CiA 301) stack of the nodes.

Owns SDO server and codecs (:mod:`bus.cia301.sdo`: expedited, segmented, block, abort codes),
NMT and heartbeat (:mod:`bus.cia301.nmt`), EMCY (:mod:`bus.cia301.emcy`), PDO communication and
mapping parameters with the SYNC consumer (:mod:`bus.cia301.pdo`), and the node runtime
with its object store (:mod:`bus.cia301.slave`).  It is the independent implementation that the
``canopen`` library on the host checks.

May import: the top-level modules of ``bus`` (errors, units, objects), python-can, canopen's EDS
import.  Never ``bus.transports``, ``firmware_model``, ``host`` or ``plant``.
"""

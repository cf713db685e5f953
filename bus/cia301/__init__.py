"""bus.cia301: the hand-written CANopen (CiA 301) stack of the nodes.

Owns SDO server and codecs (:mod:`bus.cia301.sdo`: expedited, segmented, block, abort codes),
NMT and heartbeat (:mod:`bus.cia301.nmt`), EMCY and the error history (:mod:`bus.cia301.emcy`), a
node's EMCY producer (:mod:`bus.cia301.emcy_producer`: 0x1014, 0x1015 inhibit time), the
PDO service and SYNC consumer (:mod:`bus.cia301.pdo`) with the PDO parameters and their write
rules (:mod:`bus.cia301.pdo_parameters`), the EDS-backed object store
(:mod:`bus.cia301.object_store`), store/restore of parameters (:mod:`bus.cia301.storage`) and the node
runtime (:mod:`bus.cia301.slave`, with a trial's io ticks answered by the transport:
:mod:`bus.cia301.answering`).  It is the independent implementation that the
``canopen`` library on the host checks.

May import: the top-level modules of ``bus`` (errors, units, objects), python-can, canopen's EDS
import.  Never ``bus.transports``, ``firmware_model``, ``host`` or ``plant``.
"""

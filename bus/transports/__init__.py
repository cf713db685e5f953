"""bus.transports: how the logical channels (fieldbus, io) are carried.

Owns the transport configuration (:mod:`bus.transports.config`: socketcan, udp_multicast in a
private network namespace, the zero-privilege hub, python-can's virtual bus), python-can's
udp_multicast bus as the project opens it (:mod:`bus.transports.udp_multicast`: a receive buffer
for bursts, every lost datagram reported as a bus error), the ``--inject`` fault language and the
hub's frame faults (:mod:`bus.transports.fault_inject`), and the hub, a python-can interface
``ilcrig_hub`` (the subpackage :mod:`bus.transports.hub`).  Code above ``bus`` never knows which
transport it runs on.

May import: the top-level modules of ``bus``, :mod:`bus.transports.hub` and python-can.  Never
``bus.cia301``, ``firmware_model``, ``host`` or ``plant``.
"""

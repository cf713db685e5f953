"""bus.transports: how the logical channels (fieldbus, io) are carried.

Owns the transport configuration (:mod:`bus.transports.config`: socketcan, udp_multicast in a
private network namespace, the zero-privilege hub, python-can's virtual bus) and the hub, a
python-can interface ``ilcrig_hub`` (wire format, client bus and server).  Code above ``bus``
never knows which transport it runs on.

May import: the top-level modules of ``bus`` and python-can.  Never ``bus.cia301``,
``firmware_model``, ``host`` or ``plant``.
"""

"""bus.transports.hub: the zero-privilege CAN hub, a python-can interface ``ilcrig_hub``.

Owns one hub process (no root, no kernel module) that carries logical CAN buses between its
members over a Unix socket or loopback TCP, and the client that joins one of them. Its modules:

* :mod:`~bus.transports.hub.wire`: protocol constants, handshake, hub errors
* :mod:`~bus.transports.hub.addresses`: hub addresses and channel strings, the loopback rule, connecting
* :mod:`~bus.transports.hub.owner`: who may use a hub — its user and root: the private socket folder,
  socket modes, the peer's user on both ends
* :mod:`~bus.transports.hub.records`: frames and filters as records (encode, decode)
* :mod:`~bus.transports.hub.client`: :class:`HubBus`, the python-can interface ``ilcrig_hub`` (entry point)
* :mod:`~bus.transports.hub.server`: :class:`HubServer`, the event loop, connections and handshakes
* :mod:`~bus.transports.hub.routing`: members, logical buses, fan-out, delivery queues, frame faults
* :mod:`~bus.transports.hub.bus_time`: bus time — arbitration order, bit times, the virtual bus clock
* :mod:`~bus.transports.hub.core`: the adapter to the C data plane ``_hubcore`` (``_hubcore.c``, built by setup.py)
* :mod:`~bus.transports.hub.stats`: per-bus counters and the stats query
* :mod:`~bus.transports.hub.process`: :func:`start_hub`, the hub as a child process (:class:`HubHandle`)
* :mod:`~bus.transports.hub.serve`: :func:`run_hub` with :class:`HubOptions`, the hub process (its
  command line is ``ilcrig hub``, :mod:`host.cli.hub`)

May import: the top-level modules of ``bus``, :mod:`bus.transports.fault_inject` (the ``--inject``
frame faults), python-can and numpy.  Never ``bus.cia301``, ``firmware_model``, ``host`` or
``plant``.  Importing the package imports none of its modules (a client does not load the server).
"""

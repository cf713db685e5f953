"""host.nodes: the host's clients of the nodes on the fieldbus.

Owns :class:`~host.nodes.drive_client.DriveClient` (configure, tables, enable, arm, recorder
upload of one drive), :class:`~host.nodes.plant_client.PlantClient` (the plant's test-bench
node) and :class:`~host.nodes.sdo_access.SdoAccess` (object access through the ``canopen``
library's SDO client).  Both clients work on any implementation of the object-access protocol
:class:`bus.cia301.sdo.ObjectAccess` — an SDO client or a firmware object in the same process.

May import: ``bus`` and ``bus.cia301`` (object indices, encodings), canopen.
"""

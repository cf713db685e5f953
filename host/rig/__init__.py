"""host.rig: the distributed rig, ``ilcrig run`` and ``ilcrig host``.

Owns the host role on the bus (:mod:`host.rig.host_role`: the rig bench over the ``canopen``
library, channel monitors and logs) and the launcher that starts the hub, the plant, the four
drives and the host as processes and cleans them up (:mod:`host.rig.launcher`).

May import: ``bus`` (incl. ``bus.cia301`` and ``bus.transports``), :mod:`host.nodes`,
:mod:`host.experiment`, :mod:`host.analysis`.  Never ``firmware_model`` or ``plant``: the rig
talks to drives and plant only over the bus.
"""

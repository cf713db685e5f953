"""Test helper: a hub (:class:`bus.transports.hub.server.HubServer`) serving in a thread of the test
process, so a test can read its state; stopped and joined on the way out (:func:`serving`; one on a
socket in a folder, of the data plane the test asks for: :func:`serving_in`)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from bus.transports.hub.server import HubServer


@contextmanager
def serving(server: HubServer) -> Iterator[HubServer]:
    """Serve ``server`` in a daemon thread for the ``with`` block; then wake it, join the thread
    and close the server. Fails if the thread did not end."""
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server
    finally:
        server.wake()
        thread.join(10)
        server.close()
    assert not thread.is_alive()


@contextmanager
def serving_in(folder: Path, data_plane: str, cls: type[HubServer] = HubServer) -> Iterator[HubServer]:
    """A hub of class ``cls`` on ``unix:<folder>/hub.sock`` (checked to run ``data_plane``), served
    for the ``with`` block (:func:`serving`)."""
    server = cls([f"unix:{folder}/hub.sock"])
    assert server.data_plane == data_plane
    with serving(server):
        yield server

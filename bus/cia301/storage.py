"""CiA 301 store parameters (0x1010) and restore default parameters (0x1011) of a slave.

Owns :class:`ParameterStorage`: where the saved parameters of one node live -- a JSON file per node
under a folder the node's role gives (``<folder>/node<id>.json``, kept across processes), or, with
no folder, memory (kept until the process ends) -- and the hooks of 0x1010/0x1011 on an
:class:`bus.cia301.object_store.ObjectStore` (:meth:`ParameterStorage.install`):

* the groups, by sub-index of both objects (CiA 301 §7.5.2.14/15): 1 all parameters, 2 the
  communication parameters (0x1000–0x1FFF), 3 the application parameters (0x2000–0x9FFF);
* 0x1010:n reads 1 (the node saves on command, never by itself); writing the signature "save"
  (0x65766173) saves the current values of the group's parameters, any other value is refused
  with 0x08000020;
* 0x1011:n reads 1 (defaults can be restored); writing "load" (0x64616F6C) drops the saved values
  of the group -- the EDS defaults return at the next reset (reset node: every group, reset
  communication: 0x1000–0x1FFF) and at the next boot; any other value: 0x08000020;
* a parameter is a numeric object that can be written, has no read hook (its value is its own,
  not derived from the node's state) and is not excluded by the node (its commands and
  set-points, e.g. a controlword or a target position, are not parameters);
* :meth:`ParameterStorage.restore` writes the saved values of an index range back into the
  store's values after a reset of that range (values only, no write hooks: the node applies its
  objects after a reset as it does after boot).

A file that cannot be written makes the save fail with 0x08000020 (nothing half-written: the file
is replaced atomically); a file that cannot be read at boot is logged and ignored (the defaults
apply).
"""

from __future__ import annotations

import functools
import json
import logging
from collections.abc import Collection
from pathlib import Path

from canopen.objectdictionary import ODVariable

from bus.atomic import atomic_write
from bus.cia301.object_store import Key, ObjectStore, Value
from bus.errors import AbortCode, SdoAbort

logger = logging.getLogger(__name__)

#: 0x1010 / 0x1011
STORE_INDEX = 0x1010
RESTORE_INDEX = 0x1011
#: "save" / "load" as little-endian U32
SAVE_SIGNATURE = 0x65766173
LOAD_SIGNATURE = 0x64616F6C
#: sub-index -> the index range of its group
GROUPS: dict[int, tuple[int, int]] = {1: (0x1000, 0x9FFF), 2: (0x1000, 0x1FFF), 3: (0x2000, 0x9FFF)}
_FILE_VERSION = 1


def _one() -> int:
    """0x1010:n / 0x1011:n read: 1 (saves on command / can restore)."""
    return 1


class ParameterStorage:
    """The saved parameters of one node (see the module docstring).

    :param node_id: the node (names the file).
    :param folder: where the file lives; None keeps the saved values in memory.
    :param exclude: keys that are not parameters (commands, set-points).
    """

    def __init__(self, node_id: int, folder: str | Path | None = None, exclude: Collection[Key] = ()) -> None:
        self.node_id = int(node_id)
        self.path: Path | None = None if folder is None else Path(folder) / f"node{self.node_id}.json"
        self.exclude = frozenset(exclude)
        self._saved: dict[Key, int] = self._load()

    # ------------------------------------------------------------------ persistence

    def _load(self) -> dict[Key, int]:
        if self.path is None or not self.path.exists():
            return {}
        try:
            doc = json.loads(self.path.read_text())
            if doc.get("version") != _FILE_VERSION:
                raise ValueError(f"version {doc.get('version')!r}")
            return {(int(k.split(":")[0], 16), int(k.split(":")[1])): int(v) for k, v in doc["values"].items()}
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
            logger.warning("node %d: saved parameters %s not used: %s", self.node_id, self.path, err)
            return {}

    def _write(self) -> None:
        if self.path is None:
            return
        doc = {
            "version": _FILE_VERSION,
            "node": self.node_id,
            "values": {f"{i:04X}:{s}": v for (i, s), v in sorted(self._saved.items())},
        }
        try:
            atomic_write(self.path, json.dumps(doc, indent=1) + "\n")
        except OSError as err:
            raise SdoAbort(AbortCode.CANNOT_STORE, f"cannot write {self.path}: {err}") from err

    @property
    def saved(self) -> dict[Key, int]:
        """The saved values (a copy)."""
        return dict(self._saved)

    # ------------------------------------------------------------------ the objects

    def is_parameter(self, store: ObjectStore, key: Key) -> bool:
        """True when ``key`` is a parameter of ``store`` (see the module docstring)."""
        var: ODVariable = store.vars[key]
        return (
            key not in self.exclude
            and key[0] not in (STORE_INDEX, RESTORE_INDEX)
            and var.access_type in ("rw", "wo", "rww", "rwr")
            and var.data_type in ODVariable.STRUCT_TYPES
            and key not in store.read_hooks
        )

    def save(self, store: ObjectStore, group: int) -> None:
        """Save the current values of group ``group``'s parameters.

        :raises SdoAbort: 0x08000020 the file cannot be written.
        """
        first, last = GROUPS[group]
        previous = dict(self._saved)
        for key, value in store.values.items():
            if first <= key[0] <= last and self.is_parameter(store, key) and isinstance(value, int):
                self._saved[key] = int(value)
        try:
            self._write()
        except SdoAbort:
            self._saved = previous
            raise
        logger.info("node %d: parameters 0x%04X..0x%04X saved (%s)", self.node_id, first, last, self.path or "memory")

    def drop(self, group: int) -> None:
        """Forget the saved values of group ``group`` (defaults at the next reset).

        :raises SdoAbort: 0x08000020 the file cannot be written.
        """
        first, last = GROUPS[group]
        previous = dict(self._saved)
        self._saved = {k: v for k, v in self._saved.items() if not first <= k[0] <= last}
        try:
            self._write()
        except SdoAbort:
            self._saved = previous
            raise
        logger.info("node %d: defaults of 0x%04X..0x%04X restored at the next reset", self.node_id, first, last)

    def restore(self, store: ObjectStore, first: int, last: int) -> None:
        """Write the saved values of [first, last] into ``store.values`` (after its reset); a saved
        value the EDS no longer allows is skipped."""
        for key, value in self._saved.items():
            if not first <= key[0] <= last or key not in store.vars:
                continue
            var = store.vars[key]
            if (var.min is not None and value < var.min) or (var.max is not None and value > var.max):
                logger.warning("node %d: saved 0x%04X:%d = %d outside the EDS limits: skipped", self.node_id, *key, value)
                continue
            store.values[key] = value

    def install(self, store: ObjectStore) -> None:
        """Hook 0x1010:1..3 and 0x1011:1..3 of ``store`` (those the EDS has)."""
        for group in GROUPS:
            if (STORE_INDEX, group) in store.vars:
                store.read_hooks[(STORE_INDEX, group)] = _one
                store.write_hooks[(STORE_INDEX, group)] = functools.partial(self._write_store, store, group)
            if (RESTORE_INDEX, group) in store.vars:
                store.read_hooks[(RESTORE_INDEX, group)] = _one
                store.write_hooks[(RESTORE_INDEX, group)] = functools.partial(self._write_restore, group)

    def _write_store(self, store: ObjectStore, group: int, value: Value) -> None:
        if value != SAVE_SIGNATURE:
            raise SdoAbort(AbortCode.CANNOT_STORE, f"0x1010:{group}: write the signature 'save' (0x{SAVE_SIGNATURE:08X})")
        self.save(store, group)

    def _write_restore(self, group: int, value: Value) -> None:
        if value != LOAD_SIGNATURE:
            raise SdoAbort(AbortCode.CANNOT_STORE, f"0x1011:{group}: write the signature 'load' (0x{LOAD_SIGNATURE:08X})")
        self.drop(group)

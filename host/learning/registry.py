"""Learning laws by name: the built-in ones, the plug-ins, ``module:Class``, and classes registered in
this process.

This module owns how a law name given in ``--law``, in a TOML file or in the API becomes a class:

1. a built-in name (:data:`host.learning.names.LAWS`, the classes of :mod:`host.learning.laws`);
2. a class registered in this process with :func:`register_law` (the API's ``ilcrig.register_law``;
   such a law runs in this process only, not in the rig's host process);
3. a plug-in: an entry point of the group :data:`ENTRY_POINT_GROUP` (``ilcrig.laws``) of any
   installed distribution, ``name = "package.module:Class"`` — as python-can finds its interfaces in
   ``can.interface``.  ilcrig's own laws beyond the built-in ones (``cno-ilc``, ``adjoint-ilc``)
   are plug-ins of its own distribution;
4. ``module:Class`` (a colon in the name): imported as it is, no registration needed.

It is import-light (``importlib.metadata`` only): the command line validates a law name before
anything heavy is imported; the plug-in's module is imported when its class is asked for
(:func:`law_class`).  Every failure is a :class:`LawNameError` (:class:`bus.errors.InputError`,
a ``ValueError``) with one line naming the law.
"""

from __future__ import annotations

import importlib
import logging
from importlib import metadata
from typing import Any

from bus.errors import InputError
from host.learning.names import LAWS

logger = logging.getLogger(__name__)

__all__ = [
    "ENTRY_POINT_GROUP",
    "LawNameError",
    "law_descriptions",
    "check_law_name",
    "law_class",
    "law_names",
    "plugin_entry_points",
    "register_law",
    "registered_here",
]

#: the entry-point group of third-party learning laws
ENTRY_POINT_GROUP = "ilcrig.laws"

#: classes registered in this process: name → class
_REGISTERED: dict[str, type[Any]] = {}


class LawNameError(InputError):
    """A law name that names no law, or a plug-in that cannot be loaded (one line; bad input)."""


def plugin_entry_points() -> dict[str, metadata.EntryPoint]:
    """The installed plug-ins: entry-point name → entry point (a name of a built-in law is ignored,
    with a warning: the built-in law wins)."""
    found: dict[str, metadata.EntryPoint] = {}
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in LAWS:
            logger.warning("plug-in law %r (%s) has the name of a built-in law: ignored", ep.name, ep.value)
            continue
        found.setdefault(ep.name, ep)
    return found


def law_names() -> tuple[str, ...]:
    """Every law name this process knows: the built-in ones, then the plug-ins and the registered
    classes (sorted)."""
    extra = sorted(set(plugin_entry_points()) | set(_REGISTERED))
    return LAWS + tuple(n for n in extra if n not in LAWS)


def registered_here(name: str) -> bool:
    """True for a law registered with :func:`register_law` (known to this process only)."""
    return name in _REGISTERED and name not in plugin_entry_points()


def register_law(cls: type[Any], name: str | None = None) -> str:
    """Make ``cls`` usable by ``name`` (default: its ``name`` attribute, else its class name) in this
    process; returns the name.

    :raises LawNameError: the name of a built-in law, or a class without ``update``.
    """
    _check_class(cls, repr(name or cls))
    key = str(name or getattr(cls, "name", None) or cls.__name__)
    if key in LAWS:
        raise LawNameError(f"law {key!r}: a built-in law has that name; register the class under another name")
    if ":" in key or not key.strip():
        raise LawNameError(f"law name {key!r}: must be non-empty and without ':'")
    _REGISTERED[key] = cls
    return key


def _unknown(name: str) -> LawNameError:
    extra = [n for n in law_names() if n not in LAWS]
    plugins = f"; plug-ins: {', '.join(extra)}" if extra else ""
    return LawNameError(f"unknown law {name!r}; choose one of {', '.join(LAWS)}{plugins}; or give module:Class")


def check_law_name(name: str) -> None:
    """Raise :class:`LawNameError` unless ``name`` names a law (a ``module:Class`` is imported to
    check it; an entry point is not loaded here)."""
    if name in LAWS or name in _REGISTERED:
        return
    if ":" in name:
        law_class(name)
        return
    if name not in plugin_entry_points():
        raise _unknown(name)


def law_class(name: str) -> type[Any]:
    """The class of the law ``name`` (built-in, registered, plug-in or ``module:Class``).

    :raises LawNameError: one line naming the law and what failed.
    """
    if name in LAWS:
        from host.learning.laws import LAW_CLASSES

        return LAW_CLASSES[name]
    if name in _REGISTERED:
        return _REGISTERED[name]
    if ":" in name:
        module, _, qual = name.partition(":")
        try:
            obj: Any = importlib.import_module(module)
        except Exception as exc:  # noqa: BLE001 - any import failure is one line
            raise LawNameError(f"law {name!r}: cannot import module {module!r}: {type(exc).__name__}: {exc}") from None
        for part in qual.split("."):
            if not hasattr(obj, part):
                raise LawNameError(f"law {name!r}: module {module!r} has no {qual!r}")
            obj = getattr(obj, part)
        _check_class(obj, repr(name))
        return obj
    ep = plugin_entry_points().get(name)
    if ep is None:
        raise _unknown(name)
    try:
        cls = ep.load()
    except Exception as exc:  # noqa: BLE001 - a broken plug-in is one line
        raise LawNameError(f"law {name!r}: cannot load the plug-in {ep.value!r}: {type(exc).__name__}: {exc}") from None
    _check_class(cls, f"{name!r} (plug-in {ep.value})")
    return cls


def _check_class(cls: Any, what: str) -> None:
    if not isinstance(cls, type) or not callable(getattr(cls, "update", None)):
        raise LawNameError(f"law {what}: not a learning-law class (a class with update(trial), docs/api.md)")


def law_descriptions() -> dict[str, str]:
    """Every law this process can run by name → its one-line description (``ilcrig laws``); a
    plug-in that cannot be loaded says so in its description."""
    out = {}
    for name in law_names():
        try:
            cls = law_class(name)
            out[name] = str(getattr(cls, "description", "") or (cls.__doc__ or "").strip().splitlines()[0])
        except (ValueError, IndexError) as exc:
            out[name] = f"(cannot be loaded: {exc})"
    return out

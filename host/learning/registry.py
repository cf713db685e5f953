"""Learning laws by name: the project's laws, the plug-ins, ``module:Class``, and classes registered in
this process.

This module owns how a law name given in ``--law``, in a TOML file or in the API becomes a class, and
where it came from (:func:`law_source`):

1. a project law: a name of :data:`host.learning.names.PROJECT_LAW_NAMES`, the static table
   :data:`host.learning.laws.table.PROJECT_LAWS` (the eight classic laws, ``cno-ilc``,
   ``adjoint-ilc``).  These names resolve from the table alone: nothing installed or registered can
   take one;
2. a class registered in this process with :func:`register_law` (the API's ``ilcrig.register_law``;
   such a law runs in this process only, not in the rig's host process; a project name is refused);
3. ``module:Class`` (a colon in the name): imported as it is, no registration needed;
4. a plug-in: an entry point of the group :data:`ENTRY_POINT_GROUP` (``ilcrig.laws``) of an
   installed third-party distribution, ``name = "package.module:Class"`` — as python-can finds its
   interfaces in ``can.interface``.  A plug-in that claims a project name, or two distributions
   that claim one name, are an installation error: every lookup that needs the plug-ins (a plug-in's
   name, an unknown name, the list of names) raises it as one line naming the distribution(s), and
   it is logged as a warning once per cause.

It is import-light (``importlib.metadata`` only): the command line validates a law name before
anything heavy is imported; a law's module is imported when its class is asked for
(:func:`law_class`).  Every failure is a :class:`LawNameError` (a ``bus.errors.InputError``: one
line naming the law, exit code 2).

May import: ``bus`` and :mod:`host.learning` (names; the table of :mod:`host.learning.laws`, lazily).
"""

from __future__ import annotations

import importlib
import logging
from importlib import metadata
from typing import Any

from bus.errors import InputError
from host.learning.names import PROJECT_LAW_NAMES

logger = logging.getLogger(__name__)

__all__ = [
    "ENTRY_POINT_GROUP",
    "LawNameError",
    "law_descriptions",
    "check_law_name",
    "discover_entry_points",
    "law_class",
    "law_names",
    "law_source",
    "plugin_entry_points",
    "register_law",
    "registered_here",
]

#: the entry-point group of third-party learning laws
ENTRY_POINT_GROUP = "ilcrig.laws"

#: classes registered in this process: name → class
_REGISTERED: dict[str, type[Any]] = {}
#: the installation errors already logged (a warning once per cause, not per lookup)
_WARNED: set[str] = set()


class LawNameError(InputError):
    """A law name that names no law, a plug-in that cannot be loaded or that conflicts with another
    law, a class that cannot be registered (one line)."""


def discover_entry_points() -> list[metadata.EntryPoint]:
    """The installed entry points of :data:`ENTRY_POINT_GROUP` (the one place that asks
    ``importlib.metadata``)."""
    return list(metadata.entry_points(group=ENTRY_POINT_GROUP))


def _distribution(ep: metadata.EntryPoint) -> tuple[str, str]:
    """(name, version) of the distribution that declares ``ep`` (``?`` when unknown)."""
    dist = getattr(ep, "dist", None)
    name = version = None
    if dist is not None:
        try:
            name, version = dist.name, dist.version
        except Exception:  # noqa: BLE001 - broken metadata: the entry point is still named
            pass
    return str(name or "?"), str(version or "?")


def _which(ep: metadata.EntryPoint) -> str:
    name, version = _distribution(ep)
    return f"distribution {name!r} {version} ({ep.value})"


def _installation_error(message: str) -> LawNameError:
    """The error of a conflicting installation, logged as a warning the first time only."""
    if message not in _WARNED:
        _WARNED.add(message)
        logger.warning("%s", message)
    return LawNameError(message)


def plugin_entry_points() -> dict[str, metadata.EntryPoint]:
    """The installed plug-ins: entry-point name → entry point.

    :raises LawNameError: a plug-in claims a project law's name (naming its distribution), or two
        distributions claim one name (naming both).
    """
    found: dict[str, metadata.EntryPoint] = {}
    for ep in discover_entry_points():
        if ep.name in PROJECT_LAW_NAMES:
            raise _installation_error(
                f"plug-in law {ep.name!r} of {_which(ep)} claims the name of a project law, which cannot be "
                "replaced: uninstall it or rename its entry point"
            )
        other = found.get(ep.name)
        if other is None:
            found[ep.name] = ep
        elif (_distribution(other), other.value) != (_distribution(ep), ep.value):
            raise _installation_error(
                f"plug-in law {ep.name!r} is claimed by two distributions: {_which(other)} and {_which(ep)}; uninstall one"
            )
    return found


def law_names() -> tuple[str, ...]:
    """Every law name this process knows: the project's laws, then the plug-ins and the registered
    classes (sorted).

    :raises LawNameError: a conflicting installation (:func:`plugin_entry_points`).
    """
    extra = sorted(set(plugin_entry_points()) | set(_REGISTERED))
    return PROJECT_LAW_NAMES + tuple(extra)


def registered_here(name: str) -> bool:
    """True for a law registered with :func:`register_law` (known to this process only)."""
    return name in _REGISTERED


def register_law(cls: type[Any], name: str | None = None) -> str:
    """Make ``cls`` usable by ``name`` (default: its own ``name`` attribute, else its class name) in
    this process; returns the name.

    :raises LawNameError: the name of a project law, a name with ``:``, or a class without ``update``.
    """
    _check_class(cls, repr(name or cls))
    own = getattr(cls, "name", None)
    key = str(name or (own if isinstance(own, str) and own.strip() else None) or cls.__name__)
    if key in PROJECT_LAW_NAMES:
        raise LawNameError(
            f"law {key!r}: the name of a project law, which cannot be replaced; register the class under another name"
        )
    if ":" in key or not key.strip():
        raise LawNameError(f"law name {key!r}: must be non-empty and without ':'")
    _REGISTERED[key] = cls
    return key


def _unknown(name: str) -> LawNameError:
    extra = [n for n in law_names() if n not in PROJECT_LAW_NAMES]
    plugins = f"; plug-ins: {', '.join(extra)}" if extra else ""
    return LawNameError(f"unknown law {name!r}; choose one of {', '.join(PROJECT_LAW_NAMES)}{plugins}; or give module:Class")


def check_law_name(name: str) -> None:
    """Raise :class:`LawNameError` unless ``name`` names a law (a ``module:Class`` is imported to
    check it; an entry point is not loaded here)."""
    if name in PROJECT_LAW_NAMES or name in _REGISTERED:
        return
    if ":" in name:
        law_class(name)
        return
    if name not in plugin_entry_points():
        raise _unknown(name)


def law_class(name: str) -> type[Any]:
    """The class of the law ``name`` (project, registered, ``module:Class`` or plug-in).

    :raises LawNameError: one line naming the law and what failed.
    """
    if name in PROJECT_LAW_NAMES:
        from host.learning.laws.table import PROJECT_LAWS

        return PROJECT_LAWS[name]
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
        raise LawNameError(f"law {name!r}: cannot load the plug-in of {_which(ep)}: {type(exc).__name__}: {exc}") from None
    _check_class(cls, f"{name!r} (plug-in of {_which(ep)})")
    return cls


def law_source(name: str) -> dict[str, str]:
    """Where the law ``name`` comes from (summary.json's ``law_source``):
    ``{"name", "source": "built-in"}`` (a project law), ``{"name", "source": "plug-in",
    "distribution", "version", "entry_point"}``, ``{"name", "source": "module", "module", "class"}``
    (``module:Class``) or ``{"name", "source": "registered", "module", "class"}``.

    :raises LawNameError: as :func:`law_class`.
    """
    if name in PROJECT_LAW_NAMES:
        return {"name": name, "source": "built-in"}
    if name in _REGISTERED:
        cls = _REGISTERED[name]
        return {"name": name, "source": "registered", "module": cls.__module__, "class": cls.__qualname__}
    if ":" in name:
        module, _, qual = name.partition(":")
        return {"name": name, "source": "module", "module": module, "class": qual}
    ep = plugin_entry_points().get(name)
    if ep is None:
        raise _unknown(name)
    dist, version = _distribution(ep)
    return {"name": name, "source": "plug-in", "distribution": dist, "version": version, "entry_point": ep.value}


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

"""``ilcrig laws``: the learning laws this installation knows (built-in and plug-ins).

This module owns the ``laws`` subcommand and :func:`cmd_laws`; the names and descriptions come from
:mod:`host.learning.registry` (:func:`~host.learning.registry.law_descriptions`).

May import: what ``host.cli`` may.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any, TextIO

from bus.exit_codes import EXIT_OK

__all__ = ["add_parser", "cmd_laws", "print_laws"]


def add_parser(sub: Any) -> None:
    """``laws`` on the subcommands ``sub``."""
    lp = sub.add_parser("laws", help="list the learning laws: built-in, plug-ins (entry points ilcrig.laws)")
    lp.set_defaults(func=cmd_laws)


def cmd_laws(args: argparse.Namespace) -> int:
    """``ilcrig laws``: every law name this installation knows, with its one-line description."""
    return print_laws(sys.stdout)


def print_laws(stream: TextIO) -> int:
    """One line per law name (name, description), then where plug-ins come from; exit code 0."""
    from host.learning.registry import ENTRY_POINT_GROUP, law_descriptions

    laws = law_descriptions()
    width = max(len(n) for n in laws)
    for name, text in laws.items():
        stream.write(f"{name:<{width}}  {text}\n")
    stream.write(f"(plug-ins: entry-point group {ENTRY_POINT_GROUP}; any law also as --law module:Class)\n")
    return EXIT_OK

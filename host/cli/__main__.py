"""``python -m host.cli``: the ``ilcrig`` command (how ``ilcrig run`` starts its role processes).

This module owns nothing but the call of :func:`host.cli.command`.  May import: :mod:`host.cli`.
"""

from __future__ import annotations

import sys

from host.cli import command

sys.exit(command())

"""``python -m host.cli``: the ``ilcrig`` command (how ``ilcrig run`` starts its role processes).

This module owns nothing but the call of :func:`host.cli.main`.  May import: :mod:`host.cli`.
"""

from __future__ import annotations

import sys

from host.cli import main

sys.exit(main())

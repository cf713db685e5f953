"""The pdo transport's cross-check: the TPDOs a drive sent during a trial must carry its
recorder's samples (position counts, torque in ‰ of the rated torque, rounded as 0x6077 rounds).

May import: ``numpy``, :mod:`host.experiment.bench`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from host.experiment.bench import CyclicActuals, TrialFault

__all__ = ["check_tpdos_against_recorder"]


def check_tpdos_against_recorder(k: int, actuals: CyclicActuals, traces: Sequence[Any], rated_mnm: Sequence[int]) -> None:
    """The TPDO of tick n must carry the recorder's sample n (position, torque in ‰, rounded as
    the drive's 0x6077 rounds: half up): anything else is a fault of the data path."""
    for j, tr in enumerate(traces):
        r = int(rated_mnm[j])
        expected_permille = np.clip((2 * tr.torque_units.astype(np.int64) + r) // (2 * r), -(1 << 15), (1 << 15) - 1)
        if not np.array_equal(actuals.position_counts[:, j], tr.position_counts) or not np.array_equal(
            actuals.torque_permille[:, j], expected_permille
        ):
            raise TrialFault(f"trial {k}: drive {j + 1}'s TPDOs differ from its recorder")

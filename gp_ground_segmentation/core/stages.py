# SPDX-License-Identifier: Apache-2.0
"""The stage table: every stage of a frame in the order ``GroundSegmenter`` runs them.

Each row (``compiled.Stage``) is declared once, in its stage's module: its name, whose it is
('paper' or 'ours'), the SegmenterParams bool that turns it off (None: always runs) and the
compiled twins it registers (``compiled.Twin``: numpy reference, kernel, warm-up examples).
``GroundSegmenter`` asks the rows whether they are on; warm_up and the twin tests
(test/test_stage_table.py) iterate them, so a new row is compiled, warmed up and tested
without a list to update.
"""

from __future__ import annotations

import numpy as np

from . import anchor, coupled_surface, free_space, gp, grid, labels, length_factors, lines
from . import outliers, plateau, predict, structure, surface

STAGES = (grid.STAGES + lines.STAGES + anchor.STAGES + plateau.STAGES + length_factors.STAGES
          + gp.STAGES + outliers.STAGES + predict.STAGES + coupled_surface.STAGES
          + labels.STAGES + structure.STAGES
          + free_space.STAGES + surface.STAGES)

# the precisions of a frame's points: float32 first (every LiDAR driver's), then float64
POINT_DTYPES = (np.float32, np.float64)


def twins() -> list:
    """Every compiled twin of the table, in frame order."""
    return [twin for stage in STAGES for twin in stage.twins]


def compile_round_off(background_too: bool = False) -> None:
    """Compile (or load from numba's cache) the round-off twins (the GP step) now, the
    ``background`` ones (the GP std) only with ``background_too`` (else they are the
    background compiler's first jobs). Raises what a compilation raises."""
    for twin in twins():
        if not twin.exact:
            twin.prepare(np.float64, now=background_too or not twin.background)


def queue_exact() -> None:
    """Have the background compiler compile (or load) every exact twin for every signature a
    frame uses, float32 frames' first, each precision in frame order."""
    for dtype in POINT_DTYPES:
        for twin in twins():
            if twin.exact:
                twin.prepare(dtype)

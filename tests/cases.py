"""Small named cases with known answers, reused across the test modules."""

from __future__ import annotations

from qpscale import DESIGNS, Design

ALL_DESIGNS = [Design(shape=s, tiling=t) for s, t in DESIGNS]
GAPS = (0.0, 0.005, 0.05, 0.2)
SLANTS = ((0.0, 0.0), (60.0, 0.0), (60.0, 45.0), (60.0, 90.0), (63.4, 0.0))

# The paper's validation scene: 5x5 square array, d = 0.005 L, t = L.
PAPER_SQUARE = Design()

"""The paper's spring fidelity (formulations/substrate.md, sec. 6).

One spring per DOF: the diagonals of the isolated, self and coupling blocks, the couplings
kept only between lattice neighbours (scales whose gap-inflated tiles touch).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..tiling import _neighbour_offsets
from .calibration import Calibration


def diagonal(K: np.ndarray) -> np.ndarray:
    """The diagonal part of a block (or of a stack of blocks ``(..., 5, 5)``)."""
    return K * np.eye(K.shape[-1])


def spring_calibration(cal: Calibration, shape: str, tiling: str, gap: float) -> Calibration:
    """Diagonal blocks, nearest neighbours only."""
    near = _neighbour_offsets(shape, tiling, gap)
    keep = [c for c in cal.couplings if (*c.site, c.receiver) in set(near[c.source])]
    couplings = tuple(replace(c, K1=diagonal(c.K1)) for c in keep)
    return replace(cal, K_iso=diagonal(cal.K_iso), K0=diagonal(cal.K0), couplings=couplings)

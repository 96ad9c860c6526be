"""Substrate stiffness of rigid scales on an elastic half-space (formulations/substrate.md)."""

from .bem import PunchBlocks, isolated_block, punch_blocks, shape_pieces
from .calibration import Calibration, Coupling
from .stiffness import (
    EDGES,
    FIDELITIES,
    SubstrateModel,
    assemble,
    calibrate,
    check_positive_definite,
    coupling_ratio,
    dimensional_stiffness,
    factor_stiffness,
    stiffness_matrix,
)

__all__ = [
    "EDGES",
    "FIDELITIES",
    "Calibration",
    "Coupling",
    "PunchBlocks",
    "SubstrateModel",
    "assemble",
    "calibrate",
    "check_positive_definite",
    "coupling_ratio",
    "dimensional_stiffness",
    "factor_stiffness",
    "isolated_block",
    "punch_blocks",
    "shape_pieces",
    "stiffness_matrix",
]

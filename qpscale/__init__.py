"""qpscale: 3D mechanics of scaled skins with exact contact as a QP per load increment."""

from .errors import InvalidDesign, QpscaleError, QpscaleWarning, SolverFailure, SolverUnavailable
from .geometry import SHAPES, Prism, base_polygon, convex_pieces, rotation_matrix
from .tiling import DESIGNS, TILINGS_OF, Design, Patch, build_patch

__version__ = "0.1.0"

__all__ = [
    "DESIGNS",
    "SHAPES",
    "TILINGS_OF",
    "Design",
    "InvalidDesign",
    "Patch",
    "Prism",
    "QpscaleError",
    "QpscaleWarning",
    "SolverFailure",
    "SolverUnavailable",
    "base_polygon",
    "build_patch",
    "convex_pieces",
    "rotation_matrix",
    "__version__",
]

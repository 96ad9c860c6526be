"""qpscale: 3D mechanics of scaled skins with exact contact as a QP per load increment.

The notebook API (``qpscale.api``): ``geometry``, ``substrate``, ``puncture`` and ``flexure`` take
the parameters of the ``qpscale`` subcommands of the same names and return
frozen results with ``to_dict()`` (the command's JSON) and ``curve_frame()`` (a DataFrame).  Units
and the JSON contract: docs/units.md and docs/cli.md.  ``import qpscale`` loads numpy and the
geometry only; the solvers, the substrate model and pandas are imported when a computation runs.

``qpscale.puncture`` and ``qpscale.flexure`` are the API functions; ``qpscale.geometry`` and
``qpscale.substrate`` are modules of the package, so their API functions are re-exported as
``design_geometry`` and ``substrate_stiffness`` (or ``from qpscale.api import geometry, substrate``).
"""

from __future__ import annotations

from typing import Any

from .errors import InvalidDesign, QpscaleError, QpscaleWarning, SolverFailure, SolverUnavailable
from .geometry import SHAPES, Prism, base_polygon, convex_pieces, rotation_matrix
from .tiling import DESIGNS, TILINGS_OF, Design, Patch, build_patch

__version__ = "0.1.0"

_API = {
    "puncture": "puncture",
    "flexure": "flexure",
    "design_geometry": "geometry",
    "substrate_stiffness": "substrate",
    "GeometryReport": "GeometryReport",
    "SubstrateReport": "SubstrateReport",
    "PunctureReport": "PunctureReport",
    "FlexureReport": "FlexureReport",
}


def __getattr__(name: str) -> Any:
    # Bound on first use, so that ``import qpscale`` does not import the API's dependencies.
    if name in _API:
        from . import api

        return getattr(api, _API[name])
    raise AttributeError(f"module 'qpscale' has no attribute {name!r}")


__all__ = [
    "DESIGNS",
    "SHAPES",
    "TILINGS_OF",
    "Design",
    "FlexureReport",
    "GeometryReport",
    "InvalidDesign",
    "Patch",
    "Prism",
    "PunctureReport",
    "QpscaleError",
    "QpscaleWarning",
    "SolverFailure",
    "SolverUnavailable",
    "SubstrateReport",
    "base_polygon",
    "build_patch",
    "convex_pieces",
    "design_geometry",
    "flexure",
    "puncture",
    "rotation_matrix",
    "substrate_stiffness",
    "__version__",
]

"""Contact between rigid scales (formulations/contact.md): detection, rows, symmetry.

The public API is re-exported here, so ``from qpscale.contact import detect_contacts`` is all a
caller needs.  Where things live:

- :mod:`.detection`: the settings, the contact set of a configuration and how it is found
  (both formulations, the feature formulation's axis choice), and the overlap depth;
- :mod:`.rows`: the linearised rows of a contact set (gap Jacobian) and their contact forces;
- :mod:`.placement`: the convex pieces of the scales, in body frame and placed by the DOFs;
- :mod:`.separation`: the separating-axis test between placed pieces;
- :mod:`.clipping`: the feature formulation's contact points (face clipping, edge-edge points);
- :mod:`.planes`: the plane formulation's separating planes and their vertex rows;
- :mod:`.symmetry`: a mirror symmetry held on a path (DOF modes, the planes' images).
"""

from .clipping import KIND_NAMES
from .detection import FORMULATIONS, MODES, ContactSet, ContactSettings, detect_contacts, penetration
from .planes import Planes
from .rows import contact_forces, gap_jacobian
from .symmetry import Mirror, map_dofs

__all__ = [
    "FORMULATIONS",
    "KIND_NAMES",
    "MODES",
    "ContactSet",
    "ContactSettings",
    "Mirror",
    "Planes",
    "contact_forces",
    "detect_contacts",
    "gap_jacobian",
    "map_dofs",
    "penetration",
]

"""ParaView output of the flexure path: membrane, scales and contact forces per plate position.

Implements the output of formulations/membrane.md section 10: one .vtu per part and plate
position, indexed by a .pvd whose time value is the plate displacement w (in L).  The membrane
is its hexahedral mesh with the nodal displacement recovered from the condensed solution
(eq. (7)); scales and contact points are written by :mod:`qpscale.export_vtk`.
"""

from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np
from skfem.io.meshio import to_meshio

from .export_vtk import contacts_mesh, scales_mesh, write_series
from .geometry import Array


def membrane_mesh(model: object, z: Array) -> meshio.Mesh:
    """The membrane's hexahedra with ``displacement`` ``(N, 3)`` (L) for retained DOFs ``z``.

    ``model`` is a :class:`qpscale.experiments.flexure.FlexureModel`.
    """
    mesh = to_meshio(model.mm.mesh)  # type: ignore[attr-defined]
    u = model.cond.displacement(z)  # type: ignore[attr-defined]
    return meshio.Mesh(mesh.points, mesh.cells, point_data={"displacement": np.asarray(u, dtype=float)})


def flexure_frames(result: object) -> tuple[list[dict[str, meshio.Mesh]], list[float]]:
    """One frame (part name -> mesh) per plate position, starting at the unloaded state."""
    model = result.extras["model"]  # type: ignore[attr-defined]
    states = result.extras["states"]  # type: ignore[attr-defined]
    z0 = np.zeros(len(model.cond.retained))
    frames, times = [], []
    for w, z, cs, lam in [(0.0, z0, None, np.zeros(0))] + [(s.w, s.z, s.contacts, s.lam) for s in states]:
        frame = {"membrane": membrane_mesh(model, z)}
        if model.patch is not None:
            frame["scales"] = scales_mesh(model.patch, z[: model.n_q].reshape(-1, 5))
            frame["contacts"] = contacts_mesh(cs, lam)
        frames.append(frame)
        times.append(float(w))
    return frames, times


def write_flexure_series(result: object, directory: str | Path) -> Path:
    """Write the flexure path as a ParaView series in ``directory``; returns the .pvd path."""
    frames, times = flexure_frames(result)
    return write_series(directory, "flexure", frames, times)

"""ParaView output of the three-point bending test: membrane, scales and contact forces per increment.

Implements the output of formulations/membrane.md sec. 8 (the states of the curve): the membrane
as hexahedra with the nodal displacement of ``Condensed.displacement`` (eq. (8)), the bonded
scales as prisms lifted onto the membrane's top face z = H, and the scale-scale contact forces
as points with vectors; one .vtu per part and increment plus a .pvd index (qpscale.export_vtk).
"""

from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np

from .export_vtk import contacts_mesh, scales_mesh, write_series


def membrane_mesh(model: object, z: np.ndarray) -> meshio.Mesh:
    """The membrane's hexahedra with ``displacement`` ``(N, 3)`` (in L) for retained DOFs ``z``."""
    from skfem.io.meshio import to_meshio

    mesh = to_meshio(model.mm.mesh)  # type: ignore[attr-defined]
    u = model.cond.displacement(np.asarray(z))  # type: ignore[attr-defined]
    # to_meshio reorders the hexahedra's nodes but keeps the node numbering, so u maps one to one.
    return meshio.Mesh(mesh.points, mesh.cells, point_data={"displacement": u})


def _lift(mesh: meshio.Mesh, height: float) -> meshio.Mesh:
    points = np.array(mesh.points, dtype=float)
    points[:, 2] += height
    return meshio.Mesh(points, mesh.cells, point_data=mesh.point_data, cell_data=mesh.cell_data)


def flexure_frames(result: object) -> tuple[list[dict[str, meshio.Mesh]], list[float]]:
    """One dict part -> mesh per converged plate position; the time value is the deflection (L).

    Uses ``result.extras["states"]`` when the flexure run kept its states, else the final one.
    """
    extras = result.extras  # type: ignore[attr-defined]
    model = extras["model"]
    states = extras.get("states")
    if states:
        steps = [(s.w, s.z, s.contacts, s.lam) for s in states]
    else:
        steps = [(float(result.deflection[-1]), result.z_final, None, np.zeros(0))]  # type: ignore[attr-defined]
    H = model.setup.membrane.height
    frames = []
    for _, z, cs, lam in steps:
        frame = {"membrane": membrane_mesh(model, z)}
        if model.patch is not None:
            q = np.asarray(z)[: model.n_q].reshape(-1, 5)
            frame["scales"] = _lift(scales_mesh(model.patch, q), H)
            frame["contacts"] = _lift(contacts_mesh(cs, lam), H)
        frames.append(frame)
    return frames, [float(s[0]) for s in steps]


def write_flexure_series(result: object, directory: str | Path) -> Path:
    """The flexure curve as a ParaView series (.pvd plus one .vtu per part and increment)."""
    frames, times = flexure_frames(result)
    return write_series(directory, "flexure", frames, times)

"""ParaView output through meshio: one .vtu per increment and a .pvd series.

Implements the output described in formulations/puncture.md section 2 (what a state holds):
scales as prism cells (the dart as its two convex pieces) with the displacement of every vertex,
and contact forces as vertex cells carrying the force vector on the second body of each pair.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from xml.sax.saxutils import quoteattr

import meshio
import numpy as np

from .contact import ContactSet
from .geometry import rotation_matrix
from .tiling import Patch


def _prism_cells(nb: int) -> list[tuple[str, np.ndarray]]:
    """VTK cells of a convex prism with ``nb`` base vertices (base 0..nb-1, top nb..2nb-1).

    A quadrilateral prism is one hexahedron (base counter-clockwise seen from above); any other
    is a fan of wedges, whose base triangle VTK wants clockwise seen from above.  meshio writes
    no hexagonal-prism cell, hence the fan for the hexagon.
    """
    if nb == 4:
        return [("hexahedron", np.arange(8))]
    return [("wedge", np.array([0, k + 1, k, nb, nb + k + 1, nb + k])) for k in range(1, nb - 1)]


def scales_mesh(patch: Patch, q: np.ndarray) -> meshio.Mesh:
    """The scales at configuration ``q`` ``(n, 5)`` as prism cells with point displacements."""
    points, ref = [], []
    cells: dict[str, list[np.ndarray]] = {}
    ids: dict[str, list[int]] = {}
    count = 0
    for i in range(patch.n_scales):
        c = np.append(patch.centroids[i], 0.0)
        R = rotation_matrix(q[i, 3:5])
        for prism in patch.convex_prisms(i):
            X, nb = prism.vertices, prism.n_base
            points.append(c + q[i, :3] + X @ R.T)
            ref.append(c + X)
            for kind, order in _prism_cells(nb):
                cells.setdefault(kind, []).append(count + order)
                ids.setdefault(kind, []).append(i)
            count += 2 * nb
    pts = np.vstack(points)
    blocks = [(kind, np.array(conn)) for kind, conn in cells.items()]
    return meshio.Mesh(
        pts,
        blocks,
        point_data={"displacement": pts - np.vstack(ref)},
        cell_data={"scale": [np.array(ids[kind]) for kind in cells]},
    )


def contacts_mesh(cs: ContactSet | None, lam: np.ndarray) -> meshio.Mesh:
    """Contact points as vertex cells with ``force`` (on body b, F*) and ``gap`` (L)."""
    if cs is None or cs.m == 0:
        pts = np.zeros((0, 3))
        return meshio.Mesh(
            pts,
            [("vertex", np.zeros((0, 1), dtype=int))],
            point_data={"force": np.zeros((0, 3)), "gap": np.zeros(0)},
        )
    lam = np.asarray(lam) if len(lam) == cs.m else np.zeros(cs.m)
    return meshio.Mesh(
        cs.xb,
        [("vertex", np.arange(cs.m).reshape(-1, 1))],
        point_data={"force": lam[:, None] * cs.normal, "gap": np.asarray(cs.gap)},
    )


def write_series(
    directory: str | Path, name: str, frames: Sequence[dict[str, meshio.Mesh]], times: Sequence[float]
) -> Path:
    """Write ``frames`` (one dict part-name -> mesh per time) as .vtu files and one .pvd index.

    Frames of an earlier series of the same ``name`` in ``directory`` are removed first (a reused
    directory must not hold frames the new index does not list), and the index is written last,
    through a temporary file and a rename: a ``.pvd`` exists only when every frame it lists does.
    """
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    pvd = out / f"{name}.pvd"
    pvd.unlink(missing_ok=True)
    for stale in out.glob(f"{name}_*.vtu"):
        stale.unlink()
    rows = []
    for k, (frame, t) in enumerate(zip(frames, times)):
        for part, (label, mesh) in enumerate(frame.items()):
            fname = f"{name}_{label}_{k:04d}.vtu"
            meshio.write(out / fname, mesh, file_format="vtu")
            rows.append(
                f'    <DataSet timestep="{t:.12g}" part="{part}" name={quoteattr(label)} file="{fname}"/>'
            )
    tmp = pvd.with_name(f".{pvd.name}.{os.getpid()}.tmp")
    tmp.write_text(
        '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n'
        + "\n".join(rows)
        + "\n  </Collection>\n</VTKFile>\n"
    )
    os.replace(tmp, pvd)
    return pvd


def write_puncture_series(result: object, directory: str | Path) -> Path:
    """The puncture path as a ParaView series; the time value is the puncture depth w* (in L).

    With separating planes the contact forces are the stated rule's, the least-norm member of each
    state's multiplier set (formulations/stability.md sec. 7, "The reported forces"), the same from
    every backend; with feature rows or the penalty baseline, the path's own."""
    from .experiments.puncture import reported_forces

    setup = result.setup  # type: ignore[attr-defined]
    patch = setup.design.patch()
    states = result.states  # type: ignore[attr-defined]
    frames = []
    for s in states:
        cs, lam = reported_forces(setup, s, result.load_point)  # type: ignore[attr-defined]
        frames.append({"scales": scales_mesh(patch, s.q), "contacts": contacts_mesh(cs, lam)})
    return write_series(directory, "puncture", frames, [s.delta for s in states])

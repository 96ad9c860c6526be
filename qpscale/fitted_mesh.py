"""A footprint-fitted hexahedral mesh of the flexure membrane (formulations/membrane.md sec. 9d).

The tensor mesh of ``experiments.flexure`` can put grid lines only at scale edges parallel to x
or y; along oblique edges (triangle, dart and hexagon flanks, trapezoid legs) the free strip
between two bonded footprints is whatever the grid leaves.  This mesh follows the footprints:
in the plane, quadrilaterals built by gmsh from

- a structured strip in every gap between two facing edges (``n`` elements across the gap d);
- a structured ring inside every footprint along its hinge edges (those not parallel to the
  bending direction), graded geometrically from the gap's element size away from the edge;
- lines along the roller axes and at graded offsets beside them (the contact band is resolved
  across the rollers and coarse along them, as in the tensor mesh);
- unstructured triangles elsewhere (footprint cores, gap junctions, the membrane's rim);

subdivided once (a quadrilateral into four, a triangle into three quadrilaterals), then extruded
over the graded layers of the tensor mesh down to ``SLAB_DEPTH`` under the top face; below it the
membrane is a tensor slab, and the fitted slab's bottom nodes follow its top face by the dual
mortar projection (``mortar_weights``, membrane.md sec. 9e).  gmsh is a dependency of qpscale;
its library loads the system's OpenGL and X11 libraries.

``qpscale flexure --mesh fitted`` runs it, and ``qpscale paper`` runs on it every flexure scene
whose design has oblique edges (sec. 9e: their reductions are converged along the gaps there).
"""

from __future__ import annotations

import meshio
import numpy as np
import scipy.sparse as sp
import shapely
from shapely.geometry import Point, Polygon, box
from skfem import MeshHex
from skfem.io.meshio import from_meshio

from .errors import InvalidDesign
from .experiments.flexure import FlexureSetup, mesh_membrane
from .membrane import MembraneMesh, Slaves, graded_axis, layers
from .tiling import Patch

Array = np.ndarray

#: Width of the graded ring inside a footprint along each hinge edge, in L (halved for a footprint
#: too narrow for it, e.g. one clipped by the membrane's rim).
RING_WIDTH = 0.25
#: Half-width of the band of lines beside each roller axis, in L (the rows' zone is 0.2 L wide).
ROLLER_BAND = 0.2
#: Depth of the fitted slab under the top face, in L (``fitted_mesh``): below the first layer level
#: at least this deep the membrane is a tensor slab (membrane.md sec. 9e).
SLAB_DEPTH = 0.3


def _ccw(P: Array) -> Array:
    a = np.sum(P[:, 0] * np.roll(P[:, 1], -1) - np.roll(P[:, 0], -1) * P[:, 1])
    return P if a > 0 else P[::-1]


def inset(P: Array, deltas: Array) -> Array:
    """Mitred inward offset of a counter-clockwise polygon, edge ``i`` moved by ``deltas[i]``."""
    E = np.roll(P, -1, axis=0) - P
    T = E / np.linalg.norm(E, axis=1)[:, None]
    N = np.column_stack([-T[:, 1], T[:, 0]])  # inward normals of a ccw polygon
    Q = np.empty_like(P)
    for i in range(len(P)):  # vertex i joins edges i-1 and i
        a0, b0 = P[i - 1] + deltas[i - 1] * N[i - 1], P[i] + deltas[i] * N[i]
        s = np.linalg.solve(np.column_stack([T[i - 1], -T[i]]), b0 - a0)
        Q[i] = a0 + s[0] * T[i - 1]
    return Q


def gap_strips(P: list[Array], pairs: Array, gap: float, tol: float = 1e-6) -> list[Polygon]:
    """The quadrilateral between every two facing (antiparallel, ``gap`` apart) edges of a
    neighbour pair, over the part where the edges overlap."""
    out = []
    for i, j in pairs:
        for a0, a1 in zip(P[i], np.roll(P[i], -1, axis=0)):
            ta = (a1 - a0) / np.linalg.norm(a1 - a0)
            na = np.array([ta[1], -ta[0]])  # outward for a ccw polygon
            for b0, b1 in zip(P[j], np.roll(P[j], -1, axis=0)):
                tb = (b1 - b0) / np.linalg.norm(b1 - b0)
                if ta @ tb > -1 + 1e-9 or abs((b0 - a0) @ na - gap) > tol:
                    continue
                s0, s1 = sorted([(b0 - a0) @ ta, (b1 - a0) @ ta])
                lo, hi = max(0.0, s0), min(float(np.linalg.norm(a1 - a0)), s1)
                if hi - lo > 1e-9:
                    p0, p1 = a0 + lo * ta, a0 + hi * ta
                    out.append(Polygon([p0, p1, p1 + gap * na, p0 + gap * na]))
    return out


def _rings(P: list[Array], half: tuple[float, float], axis: int, gap: float):
    """Footprints clipped to the membrane, their cores and their hinge-edge ring trapezoids
    ``(polygon, origin, tangent, inward normal, width)``."""
    rect = box(-half[0], -half[1], half[0], half[1])
    rings, cores = [], []
    for p0 in P:
        clip = Polygon(p0).intersection(rect)
        if clip.area < 1e-9:
            continue
        p = _ccw(np.asarray(shapely.remove_repeated_points(clip).exterior.coords)[:-1])
        E = np.roll(p, -1, axis=0) - p
        rim = np.array(
            [
                np.any(np.all(np.abs(np.abs(p[[e, (e + 1) % len(p)]]) - half) < 1e-9, axis=0))
                for e in range(len(p))
            ]
        )
        # Edges parallel to the bending direction do not open as hinges: the tensor mesh does not
        # grade them either (membrane.md sec. 2), and the square arrays agree (sec. 9d).
        hinge = np.abs(E[:, 1 - axis]) > 1e-9 * np.linalg.norm(E, axis=1)
        ringed = hinge & ~rim
        width = RING_WIDTH
        while True:
            q = inset(p, np.where(ringed, width, 0.0))
            Eq = np.roll(q, -1, axis=0) - q
            core = Polygon(q)
            if (
                core.is_valid
                and core.area > 0
                and Polygon(p).buffer(1e-9, join_style="mitre").contains(core)
                and np.all(np.sum(Eq * E, axis=1) > 0)
            ):
                break
            width /= 2
            if width < 4 * gap:  # a sliver cut by the membrane's rim: no ring
                ringed[:] = False
                q = p
                break
        cores.append(q)
        for e in np.flatnonzero(ringed):
            a, b = p[e], p[(e + 1) % len(p)]
            t = (b - a) / np.linalg.norm(b - a)
            trapezoid = Polygon([a, b, q[(e + 1) % len(p)], q[e]])
            rings.append((trapezoid, a, t, np.array([-t[1], t[0]]), width))
    return rings, cores


def _signed_areas(xy: Array, quads: Array) -> Array:
    x = xy[quads]
    return 0.5 * np.sum(
        x[..., 0] * np.roll(x[..., 1], -1, axis=1) - np.roll(x[..., 0], -1, axis=1) * x[..., 1], axis=1
    )


def _corner_turns(xy: Array, quads: Array) -> Array:
    """``(m, 4)`` cross products of the two edges at each corner of each quadrilateral."""
    x = xy[quads]
    e_in = x - np.roll(x, 1, axis=1)
    e_out = np.roll(x, -1, axis=1) - x
    return e_in[..., 0] * e_out[..., 1] - e_in[..., 1] * e_out[..., 0]


def _oriented(xy: Array, quads: Array, area: float) -> Array:
    """The quadrilaterals turned counter-clockwise, after checking that they are a valid mesh.

    gmsh orients a surface's elements by the surface's normal, which the fragment leaves facing
    +z or -z, so each element is turned on its own.  That is only a relabelling if the element is
    convex (a bilinear quadrilateral's Jacobian is positive at its four corners exactly then) and
    the elements do not overlap, which the sum of their areas against the rectangle's shows (a
    folded element is counted twice).
    """
    flip = _signed_areas(xy, quads) < 0
    quads = np.where(flip[:, None], quads[:, ::-1], quads)
    turns = _corner_turns(xy, quads)
    bad = int(np.sum(np.any(turns <= 0, axis=1)))
    if bad:
        raise InvalidDesign("mesh", f"fitted ({bad} non-convex or degenerate quadrilaterals)", "a valid mesh")
    total = float(np.sum(_signed_areas(xy, quads)))
    if abs(total - area) > 1e-9 * area:
        raise InvalidDesign(
            "mesh", f"fitted (elements cover {total:.12g} L^2, not {area:.12g})", "a valid mesh"
        )
    return quads


def _progression_count(width: float, first: float, ratio: float) -> int:
    return max(1, int(np.ceil(np.log(1 + width * (ratio - 1) / first) / np.log(ratio) - 1e-9)))


def fitted_quads(
    patch: Patch,
    length: float,
    width: float,
    *,
    gap_elements: int = 2,
    along: float = 0.25,
    h: float = 0.5,
    growth: float = 1.5,
    contact_h: float = 0.05,
    span: float = 8.0,
    axis: int = 1,
) -> tuple[Array, Array]:
    """Plane nodes ``(n, 2)`` and counter-clockwise quadrilaterals ``(m, 4)`` of the top face.

    ``gap_elements`` (even) elements across each gap, ``along`` the element size along the gaps
    and rings, ``h`` elsewhere, rings graded from ``d / gap_elements`` by ``growth`` per element,
    roller bands from ``contact_h``; ``axis`` is the bending direction (1 for load line x).
    """
    try:
        import gmsh
    except (ImportError, OSError) as err:  # pragma: no cover - gmsh absent, or its libraries
        raise InvalidDesign(
            "mesh",
            "fitted",
            "gmsh that loads (its library needs the system's OpenGL and X11 libraries, e.g. Debian's "
            f"libglu1-mesa, libxcursor1, libxft2, libxinerama1: {err})",
        ) from err
    if gap_elements % 2:
        raise InvalidDesign("gap_elements", gap_elements, "an even number (the quads are subdivided once)")
    d = patch.design.gap
    if d <= 0:
        raise InvalidDesign("gap", d, "(0, 1) L for a fitted mesh")
    half = (length / 2, width / 2)
    P = [_ccw(np.asarray(b, dtype=float)) for b in patch.base]
    strips = gap_strips(P, patch.neighbours, d)
    rings, cores = _rings(P, half, axis, d)
    # Sizes before the subdivision, which halves every element: twice the targets, and the ring's
    # growth squared (each element is then split into two equal ones).
    first, along2, ratio = 2 * d / gap_elements, 2 * along, growth**2
    # Not interruptible: gmsh would install a SIGINT handler, which only the main thread may do (a
    # Dask worker runs its tasks in another one).
    gmsh.initialize(["-noenv"], readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("membrane")
        occ, mesh = gmsh.model.occ, gmsh.model.mesh

        def surface(xy: Array) -> int:
            pts = [occ.addPoint(x, y, 0) for x, y in xy]
            lines = [occ.addLine(pts[k], pts[(k + 1) % len(pts)]) for k in range(len(pts))]
            return occ.addPlaneSurface([occ.addCurveLoop(lines)])

        tools = [(2, surface(np.asarray(r[0].exterior.coords)[:-1])) for r in rings]
        tools += [(2, surface(q)) for q in cores]
        tools += [(2, surface(np.asarray(s.exterior.coords)[:-1])) for s in strips]
        offsets, size, o = [0.0], 2 * contact_h, 0.0
        while o + size < ROLLER_BAND:
            o += size
            offsets += [o, -o]
            size *= growth
        for c in [sign * span / 2 + off for sign in (-1, 1) for off in offsets]:
            a, b = ((-half[0], c), (half[0], c)) if axis == 1 else ((c, -half[1]), (c, half[1]))
            tools.append((1, occ.addLine(occ.addPoint(*a, 0), occ.addPoint(*b, 0))))
        occ.fragment([(2, occ.addRectangle(-half[0], -half[1], 0, length, width))], tools)
        occ.synchronize()
        rect = box(-half[0], -half[1], half[0], half[1])
        outside = [
            e for e in gmsh.model.getEntities(2) if not rect.contains(Point(occ.getCenterOfMass(*e)[:2]))
        ]
        occ.remove(outside, recursive=True)
        occ.synchronize()
        loose = [e for e in gmsh.model.getEntities(1) if not len(gmsh.model.getAdjacencies(*e)[0])]
        if loose:
            occ.remove(loose, recursive=True)
            occ.synchronize()
        count: dict[int, int] = {}

        def corners(s: int) -> tuple[list[int], Array]:
            """The surface's points in cyclic order (by angle about their mean)."""
            pts = gmsh.model.getBoundary([(2, s)], combined=False, oriented=False, recursive=True)
            tags = sorted({t for _, t in pts})
            xy = np.array([gmsh.model.getValue(0, t, [])[:2] for t in tags])
            order = np.argsort(np.arctan2(*(xy - xy.mean(axis=0)).T[::-1]))
            return [tags[i] for i in order], xy[order]

        def curves(s: int) -> list[int]:
            return [abs(t) for _, t in gmsh.model.getBoundary([(2, s)], oriented=False)]

        def ends(c: int) -> tuple[Array, Array]:
            lo, hi = gmsh.model.getParametrizationBounds(1, c)
            return (
                np.array(gmsh.model.getValue(1, c, [lo[0]])[:2]),
                np.array(gmsh.model.getValue(1, c, [hi[0]])[:2]),
            )

        surfaces = [s for _, s in gmsh.model.getEntities(2)]
        centre = {s: Point(occ.getCenterOfMass(2, s)[:2]) for s in surfaces}
        strips_grown = [g.buffer(1e-9) for g in strips]
        rings_grown = [r[0].buffer(1e-9) for r in rings]
        # Gap strips: n/2 elements across (before subdivision), the same count on both long sides.
        for s in surfaces:
            if not any(g.contains(centre[s]) for g in strips_grown):
                continue
            tags, _ = corners(s)
            cs = curves(s)
            if len(tags) != 4 or len(cs) != 4:
                continue
            lengths = {c: occ.getMass(1, c) for c in cs}
            short = [c for c in cs if lengths[c] < 3 * d]
            if len(short) != 2:
                continue
            long_ = [c for c in cs if c not in short]
            m = max(1, int(np.ceil(np.mean([lengths[c] for c in long_]) / along2 - 1e-6)))
            for c, n in [(c, gap_elements // 2) for c in short] + [(c, m) for c in long_]:
                mesh.setTransfiniteCurve(c, n + 1)
                count[c] = n
            mesh.setTransfiniteSurface(s, cornerTags=tags)
            mesh.setRecombine(2, s)
        # Rings: graded across from the edge, the inner side carrying the outer side's nodes.
        for s in surfaces:
            owner = [r for r, grown in zip(rings, rings_grown) if grown.contains(centre[s])]
            if len(owner) != 1:
                continue
            _, o, t, nrm, w = owner[0]
            tags, xy = corners(s)
            across, along_ = (xy - o) @ nrm, (xy - o) @ t
            outer, inner = np.abs(across) < 1e-7, np.abs(across - w) < 1e-7
            if not (outer | inner).all() or inner.sum() != 2:
                continue
            # The corners: the outer side's two ends and the two inner points, in cyclic order.
            io = np.flatnonzero(outer)
            keep = set(np.flatnonzero(inner)) | {io[np.argmin(along_[io])], io[np.argmax(along_[io])]}
            corner = [tags[i] for i in range(len(tags)) if i in keep]
            total, inner_curve, sides = 0, None, []
            for c in curves(s):
                p0, p1 = ends(c)
                a0, a1 = (p0 - o) @ nrm, (p1 - o) @ nrm
                if abs(a0) < 1e-7 and abs(a1) < 1e-7:
                    if c not in count:
                        count[c] = max(1, int(np.ceil(occ.getMass(1, c) / along2 - 1e-6)))
                        mesh.setTransfiniteCurve(c, count[c] + 1)
                    total += count[c]
                elif abs(a0 - w) < 1e-7 and abs(a1 - w) < 1e-7:
                    inner_curve = c
                else:
                    sides.append((c, a0 < a1))
            if inner_curve is None or len(sides) != 2:
                continue
            k = _progression_count(w, first, ratio)
            mesh.setTransfiniteCurve(inner_curve, total + 1)
            count[inner_curve] = total
            for c, outward_first in sides:
                mesh.setTransfiniteCurve(c, k + 1, "Progression", ratio if outward_first else 1 / ratio)
            mesh.setTransfiniteSurface(s, cornerTags=corner)
            mesh.setRecombine(2, s)
        field = mesh.field.add("MathEval")
        mesh.field.setString(field, "F", f"{2 * h}")
        mesh.field.setAsBackgroundMesh(field)
        # The free regions stay triangles until the subdivision, which cuts a triangle into three
        # convex quadrilaterals whatever its shape.  Recombined into quadrilaterals first (blossom),
        # they folded elements in 3 of the 16 shape/load-line meshes (the honeycomb's rim slivers,
        # 0.03 L wide; gap strips' ends, d long, beside edges meshed at 0.5 L) with every gmsh
        # algorithm; split from triangles, all 16 pass, for 25 % more nodes (membrane.md sec. 9d).
        for name, value in [
            ("Mesh.MeshSizeExtendFromBoundary", 1),
            ("Mesh.MeshSizeFromPoints", 0),
            ("Mesh.MeshSizeFromCurvature", 0),
            ("Mesh.Algorithm", 6),  # frontal-Delaunay triangles
            ("Mesh.SubdivisionAlgorithm", 1),  # every element into quadrilaterals
        ]:
            gmsh.option.setNumber(name, value)
        mesh.generate(2)
        tags, xyz, _ = mesh.getNodes()
        index = np.full(int(tags.max()) + 1, -1)
        index[tags.astype(np.int64)] = np.arange(len(tags))
        xy = xyz.reshape(-1, 3)[:, :2]
        quads = []
        for _, s in gmsh.model.getEntities(2):
            types, _, conn = mesh.getElements(2, s)
            for kind, c in zip(types, conn):
                if mesh.getElementProperties(kind)[3] != 4:
                    raise InvalidDesign("mesh", "fitted", "quadrilaterals only (gmsh left another element)")
                quads.append(index[np.asarray(c, dtype=np.int64).reshape(-1, 4)])
    finally:
        gmsh.finalize()
    q = _oriented(xy, np.concatenate(quads), length * width)
    used = np.unique(q)
    renumber = np.full(len(xy), -1)
    renumber[used] = np.arange(len(used))
    return xy[used], renumber[q]


def _stacked(xy: Array, quads: Array, z: Array) -> tuple[Array, Array]:
    """Points and VTK hexahedra (a quad's four corners, then the four above them) stacked over
    counter-clockwise quadrilaterals at the levels ``z``."""
    n2 = len(xy)
    p = np.column_stack([np.tile(xy, (len(z), 1)), np.repeat(z, n2)])
    cells = np.concatenate(
        [np.column_stack([quads + k * n2, quads + (k + 1) * n2]) for k in range(len(z) - 1)]
    )
    return p, cells


def extrude(xy: Array, quads: Array, z: Array) -> MeshHex:
    """Hexahedra stacked over counter-clockwise quadrilaterals at the levels ``z`` (converted to
    scikit-fem's corner order by its meshio reader)."""
    p, cells = _stacked(xy, quads, z)
    return from_meshio(meshio.Mesh(p, [("hexahedron", cells)]))


def grid_quads(x: Array, y: Array) -> tuple[Array, Array]:
    """Nodes ``(nx ny, 2)`` (x fastest) and counter-clockwise quadrilaterals of a tensor grid."""
    X, Y = np.meshgrid(x, y)
    nx = len(x)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(len(y) - 1))
    a = (j * nx + i).ravel()
    return np.column_stack([X.ravel(), Y.ravel()]), np.column_stack([a, a + 1, a + 1 + nx, a + nx])


def fitted_mesh(
    setup: FlexureSetup,
    patch: Patch,
    along: float = 0.25,
    depth: float | None = SLAB_DEPTH,
) -> MembraneMesh:
    """The fitted mesh of a flexure setup with scales, with the tensor mesh's graded layers.

    ``depth`` (L): the fitted pattern runs down to the first layer level at least this far below
    the top face only; below it the membrane is a tensor slab (lines graded towards the roller
    lines as in the tensor mesh, the membrane's ``h`` elsewhere), and the
    fitted slab's bottom nodes follow the tensor slab's top face by the dual mortar projection
    (``mortar_weights``, membrane.md sec. 9e).  None: the fitted pattern through the whole
    thickness (sec. 9d).
    """
    mem = mesh_membrane(setup, patch)
    n = setup.gap_elements if setup.gap_elements is not None else 2
    xy, quads = fitted_quads(
        patch,
        mem.length,
        mem.width,
        gap_elements=n,
        along=along,
        h=mem.h,
        growth=mem.growth,
        contact_h=setup.contact_h,
        span=setup.span,
        axis=setup.axis,
    )
    z = layers(mem)
    if depth is None:
        return MembraneMesh(mem, extrude(xy, quads, z))
    if not 0.0 < depth < mem.height:
        raise InvalidDesign("depth", depth, f"(0, {mem.height}) L")
    cut = int(np.flatnonzero(z <= mem.height - depth + 1e-12)[-1])
    if cut == 0:
        raise InvalidDesign("depth", depth, "a depth that leaves a layer below the fitted slab")
    across_size, lengthwise_size = (mem.width, mem.length) if setup.axis == 1 else (mem.length, mem.width)
    s = setup.span / 2
    across = graded_axis(
        -across_size / 2, across_size / 2, mem.h, (0.0,), (-s, s), h_min=setup.contact_h, growth=mem.growth
    )
    lengthwise = graded_axis(-lengthwise_size / 2, lengthwise_size / 2, mem.h, (0.0,))
    gx, gy = (lengthwise, across) if setup.axis == 1 else (across, lengthwise)
    return MembraneMesh(mem, *slabs(xy, quads, gx, gy, z, cut))


def slabs(xy: Array, quads: Array, gx: Array, gy: Array, z: Array, cut: int) -> tuple[MeshHex, Slaves]:
    """Two slabs that meet at the level ``z[cut]``: below it hexahedra over the tensor grid
    ``gx x gy``, above it over the quadrilaterals ``(xy, quads)``; the upper slab's bottom nodes
    follow the lower slab's top face by ``mortar_weights`` (membrane.md eqs. (5c)-(5e))."""
    grid, cells = grid_quads(gx, gy)
    p_lo, c_lo = _stacked(grid, cells, z[: cut + 1])
    p_up, c_up = _stacked(xy, quads, z[cut:])
    n_lo = len(p_lo)
    mesh = from_meshio(meshio.Mesh(np.r_[p_lo, p_up], [("hexahedron", np.r_[c_lo, c_up + n_lo])]))
    W = mortar_weights(xy, quads, gx, gy)
    top_lo = cut * len(grid)  # the lower slab's top level: node j nx + i of the grid
    W = sp.hstack([sp.csr_matrix((len(xy), top_lo)), W, sp.csr_matrix((len(xy), len(p_up)))], format="csr")
    return mesh, Slaves(n_lo + np.arange(len(xy)), W)


#: A degree-5 rule on the triangle (Radon's seven points): barycentric coordinates and weights
#: (summing to 1), for the pieces of ``mortar_weights``.
_TRI_POINTS = np.array(
    [[1 / 3, 1 / 3, 1 / 3]]
    + [list(np.roll([0.059715871789770, 0.470142064105115, 0.470142064105115], k)) for k in range(3)]
    + [list(np.roll([0.797426985353087, 0.101286507323456, 0.101286507323456], k)) for k in range(3)]
)
_TRI_WEIGHTS = np.r_[0.225, [0.132394152788506] * 3, [0.125939180544827] * 3]


def _pieces(xy: Array, quads: Array, gx: Array, gy: Array) -> tuple[Array, Array, Array, Array]:
    """Each quadrilateral cut by the grid's cells: quadrature points ``(p, 2)`` and weights on
    the pieces (a degree-5 rule on a fan of each convex piece), their element and their cell
    ``(i, j)``."""
    X = xy[quads]
    lo, hi = X.min(axis=1), X.max(axis=1)
    nx, ny = len(gx) - 1, len(gy) - 1
    i0 = np.clip(np.searchsorted(gx, lo[:, 0], "right") - 1, 0, nx - 1)
    i1 = np.clip(np.searchsorted(gx, hi[:, 0], "left") - 1, 0, nx - 1)
    j0 = np.clip(np.searchsorted(gy, lo[:, 1], "right") - 1, 0, ny - 1)
    j1 = np.clip(np.searchsorted(gy, hi[:, 1], "left") - 1, 0, ny - 1)
    ni, nj = i1 - i0 + 1, j1 - j0 + 1
    e = np.repeat(np.arange(len(quads)), ni * nj)
    k = np.arange(len(e)) - np.repeat(np.cumsum(ni * nj) - ni * nj, ni * nj)
    i, j = i0[e] + k % ni[e], j0[e] + k // ni[e]
    quad = shapely.polygons(X)
    piece = shapely.intersection(quad[e], shapely.box(gx[i], gy[j], gx[i + 1], gy[j + 1]))
    keep = shapely.area(piece) > 1e-14 * shapely.area(quad)[e]
    piece, e, i, j = piece[keep], e[keep], i[keep], j[keep]
    coords, owner = shapely.get_coordinates(piece, return_index=True)
    count = np.bincount(owner, minlength=len(piece))  # ring points, the first repeated last
    start = np.cumsum(count) - count
    fans = count - 3  # triangles (v0, v_k, v_k+1) of a convex piece of count - 1 vertices
    t_owner = np.repeat(np.arange(len(piece)), fans)
    t_k = np.arange(len(t_owner)) - np.repeat(np.cumsum(fans) - fans, fans) + 1
    a, b, c = coords[start[t_owner]], coords[start[t_owner] + t_k], coords[start[t_owner] + t_k + 1]
    area = 0.5 * np.abs((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    pts = np.einsum("q,tc->tqc", _TRI_POINTS[:, 0], a) + np.einsum("q,tc->tqc", _TRI_POINTS[:, 1], b)
    pts += np.einsum("q,tc->tqc", _TRI_POINTS[:, 2], c)
    wts = area[:, None] * _TRI_WEIGHTS[None, :]
    rep = len(_TRI_WEIGHTS)
    cells = np.repeat(np.c_[i, j][t_owner], rep, axis=0)
    return pts.reshape(-1, 2), wts.ravel(), np.repeat(e[t_owner], rep), cells


def _reference(X: Array, p: Array) -> tuple[Array, Array]:
    """Bilinear shape functions ``(p, 4)`` at the points ``p`` of the convex quadrilaterals ``X
    (p, 4, 2)``: the inverse of the bilinear map by Newton's method from the centre."""
    sx, sy = np.array([-1.0, 1.0, 1.0, -1.0]), np.array([-1.0, -1.0, 1.0, 1.0])
    r = np.zeros((len(p), 2))
    for _ in range(30):
        N = 0.25 * (1 + r[:, :1] * sx) * (1 + r[:, 1:] * sy)
        dN = np.stack([0.25 * sx * (1 + r[:, 1:] * sy), 0.25 * sy * (1 + r[:, :1] * sx)], axis=1)
        res = np.einsum("pk,pkc->pc", N, X) - p
        J = np.einsum("pdk,pkc->pcd", dN, X)
        step = np.linalg.solve(J, res[..., None])[..., 0]
        r -= step
        if np.abs(step).max() < 1e-14:
            break
    N = 0.25 * (1 + r[:, :1] * sx) * (1 + r[:, 1:] * sy)
    return N, r


def mortar_weights(xy: Array, quads: Array, gx: Array, gy: Array) -> sp.csr_matrix:
    """``W (n_fine, n_grid)``: the fine nodes' displacement from the grid's, eq. (5c).

    The dual mortar projection (biorthogonal basis on the fine side).  Every quadrilateral is cut
    by the grid's cells and integrated piece by piece (``_pieces``), so the grid's hat functions
    are polynomials on each piece and integrated exactly.  On each quadrilateral ``psi = A N``
    with ``A = D M^-1`` (``M`` its mass matrix, ``D`` the diagonal of its row sums, by the same
    points), so that ``sum psi_f N_f' = delta D_f`` on those points; then ``D_f u_f =
    int psi_f u_grid``, i.e. ``W = D^-1 int psi N_grid``.  The rows reproduce a field linear in x
    and y exactly whatever the points (the biorthogonality is the discrete one), and the columns
    carry every grid node's exact share of a uniform traction (``sum psi = 1``): the two slabs
    pass the patch test, up to the quadrature of the fine shape functions on the pieces
    (membrane.md sec. 9e).  Collocating the fine nodes on the grid's bilinear field does not.
    """
    pts, w, e, cell = _pieces(xy, quads, gx, gy)
    N, _ = _reference(xy[quads][e], pts)
    n_e = len(quads)
    M = np.zeros((n_e, 4, 4))
    np.add.at(M, e, w[:, None, None] * N[:, :, None] * N[:, None, :])
    D = M.sum(axis=2)
    A = D[:, :, None] * np.linalg.inv(M)
    psi = np.einsum("pij,pj->pi", A[e], N)
    nx = len(gx)
    i, j = cell[:, 0], cell[:, 1]
    s = (pts[:, 0] - gx[i]) / (gx[i + 1] - gx[i])
    t = (pts[:, 1] - gy[j]) / (gy[j + 1] - gy[j])
    a = j * nx + i
    masters = np.column_stack([a, a + 1, a + 1 + nx, a + nx])
    Nc = np.column_stack([(1 - s) * (1 - t), s * (1 - t), s * t, (1 - s) * t])
    vals = w[:, None, None] * psi[:, :, None] * Nc[:, None, :]
    rows = np.broadcast_to(quads[e][:, :, None], vals.shape)
    cols = np.broadcast_to(masters[:, None, :], vals.shape)
    n = len(xy)
    Mt = sp.csr_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(n, nx * len(gy)))
    Dn = np.bincount(quads.ravel(), D.ravel(), minlength=n)
    return sp.csr_matrix(sp.diags(1.0 / Dn) @ Mt)

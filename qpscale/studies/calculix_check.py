"""An independent check of the membrane by a second finite element code, CalculiX (``ccx``).

Implements formulations/membrane.md sec. 9b. Both codes solve the same linear problem, one both can
state exactly: the bare membrane ``[-5, 5]^2 x [0, 1.5]`` (E = 1, nu) in three-point bending by
pressures alone, a uniform pressure of total force F = 1 down on the top strip ``|s| <= w_p/2`` and
F/2 up on each bottom strip of width ``w_s`` centred at ``s = +-span/2`` (self-equilibrated; a
statically determinate 3-2-1 pin set removes the rigid modes and carries no force).  The compared
number is the deflection of the bottom mid-line ``s = 0`` relative to the bottom support lines
``s = +-span/2`` (line averages over the load line), normalised like C_f*:
``D* = -(mean u_z(0) - mean u_z(+-span/2)) E I_m / (F L^3)``.  No load or support is a line or an
edge of a rigid body, so ``D*`` converges fast under refinement in both codes (a knife edge would
not, membrane.md sec. 1).  qpscale: trilinear hexahedra, selective reduced integration
(``qpscale.membrane``); CalculiX: 20-node hexahedra with reduced integration (C3D20R) on the same
grid lines, an element nobody here wrote.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..errors import InvalidDesign, SolverFailure, SolverUnavailable
from ..geometry import Array
from ..membrane import MembraneModel, assemble_stiffness, graded_axis
from .flexure_bench import richardson

#: C3D20 nodes as corner-sign triples on the doubled grid (ccx/Abaqus order: 8 corners, 12 mid-edges).
_C3D20 = [
    (0, 0, 0), (2, 0, 0), (2, 2, 0), (0, 2, 0), (0, 0, 2), (2, 0, 2), (2, 2, 2), (0, 2, 2),
    (1, 0, 0), (2, 1, 0), (1, 2, 0), (0, 1, 0), (1, 0, 2), (2, 1, 2), (1, 2, 2), (0, 1, 2),
    (0, 0, 1), (2, 0, 1), (2, 2, 1), (0, 2, 1),
]  # fmt: skip


@dataclass(frozen=True)
class CheckProblem:
    """The shared problem of both codes, load line x (``s = y``); lengths in L, E = 1.

    Parameters
    ----------
    nu : float
        Poisson's ratio (both codes take it as given; no cap).
    h, nz : float, int
        In-plane element size and layers through the thickness (the quadratic elements of CalculiX
        use the same grid lines, so they have twice the nodes per direction).
    span, support_width, plate_width : float
    """

    nu: float = 0.4999
    h: float = 0.5
    nz: int = 3
    span: float = 8.0
    support_width: float = 0.5
    plate_width: float = 0.5

    def __post_init__(self) -> None:
        if not 0.0 <= self.nu < 0.5:
            raise InvalidDesign("nu", self.nu, "[0, 0.5)")
        if not (0 < self.h <= 1.0 and 1 <= self.nz <= 16):
            raise InvalidDesign("h, nz", (self.h, self.nz), "h in (0, 1], nz in [1, 16]")

    def axes(self) -> tuple[Array, Array, Array]:
        """Grid lines: strip edges, support lines and the centre, in both codes."""
        s, ws, wp = self.span / 2, self.support_width / 2, self.plate_width / 2
        x = graded_axis(-5.0, 5.0, self.h)
        y = graded_axis(-5.0, 5.0, self.h, (0.0, -s - ws, -s, -s + ws, s - ws, s, s + ws, -wp, wp))
        return x, y, np.linspace(0.0, 1.5, self.nz + 1)

    @property
    def I_m(self) -> float:
        return 10.0 * 1.5**3 / 12.0


def _line_mean(x: Array, u: Array, quadratic: bool) -> float:
    """Mean of u over [x_0, x_-1]: trapezoid (linear elements) or Simpson per element (quadratic)."""
    if not quadratic:
        return float(np.trapezoid(u, x) / (x[-1] - x[0]))
    xc, uc = x[::2], u
    total = sum(
        (xc[i + 1] - xc[i]) / 6 * (uc[2 * i] + 4 * uc[2 * i + 1] + uc[2 * i + 2]) for i in range(len(xc) - 1)
    )
    return float(total / (x[-1] - x[0]))


def qpscale_deflection(problem: CheckProblem) -> float:
    """D* of ``problem`` by qpscale's membrane (hexahedra, selective reduced integration)."""
    from skfem import MeshHex

    x, y, z = problem.axes()
    model = MembraneModel(nu=min(problem.nu, 0.4999999), h=problem.h, nz=problem.nz)
    mesh = MeshHex.init_tensor(x, y, z)
    K = sp.csr_matrix(assemble_stiffness(model, mesh))
    p = mesh.p.T
    bot = np.isclose(p[:, 2], 0.0)
    f = np.zeros(3 * len(p))
    dx, dy = np.diff(x), np.diff(y)
    index = {(round(a, 9), round(b, 9), round(c, 9)): k for k, (a, b, c) in enumerate(p)}
    for face_z, pressure, faces in _pressures(problem, y):
        for i in range(len(dx)):  # bilinear face: each corner carries a quarter of the face's load
            for j in faces:
                for xi, yj in ((x[i], y[j]), (x[i + 1], y[j]), (x[i], y[j + 1]), (x[i + 1], y[j + 1])):
                    k = index[(round(xi, 9), round(yj, 9), face_z)]
                    f[3 * k + 2] += pressure * dx[i] * dy[j] / 4
    fixed = [
        3 * k + c
        for k, comps in zip(_pins(p[:, 0], p[:, 1], p[:, 2]), ((0, 1, 2), (1, 2), (2,)))
        for c in comps
    ]
    free = np.setdiff1d(np.arange(3 * len(p)), fixed)
    u = np.zeros(3 * len(p))
    u[free] = spla.spsolve(sp.csc_matrix(K[free][:, free]), f[free])

    def line(s: float) -> float:
        nodes = np.flatnonzero(bot & np.isclose(p[:, 1], s))
        nodes = nodes[np.argsort(p[nodes, 0])]
        return _line_mean(p[nodes, 0], u[3 * nodes + 2], quadratic=False)

    sc = problem.span / 2
    return -(line(0.0) - 0.5 * (line(-sc) + line(sc))) * problem.I_m


def _pressures(problem: CheckProblem, y: Array) -> list[tuple[float, float, np.ndarray]]:
    """(face z, upward traction, indices j of the y-intervals) of the plate and support pressures."""
    wp, ws, sc = problem.plate_width / 2, problem.support_width / 2, problem.span / 2
    lo, hi = y[:-1], y[1:]
    plate = np.flatnonzero((lo >= -wp - 1e-9) & (hi <= wp + 1e-9))
    sup = np.flatnonzero((np.abs(np.abs(0.5 * (lo + hi)) - sc) < ws) & (hi - lo <= 2 * ws + 1e-9))
    return [
        (1.5, -1.0 / (problem.plate_width * 10.0), plate),
        (0.0, 0.5 / (problem.support_width * 10.0), sup),
    ]


def _pins(x: Array, y: Array, z: Array) -> list[int]:
    """3-2-1 pins on the bottom: (0, 0) all, (2.5, 0) u_y u_z, (0, 2.5) u_z (statically determinate)."""
    bot = np.isclose(z, 0.0)

    def near(a: float, b: float) -> int:
        k = np.flatnonzero(bot)
        return int(k[np.argmin(np.hypot(x[k] - a, y[k] - b))])

    return [near(0.0, 0.0), near(2.5, 0.0), near(0.0, 2.5)]


def write_inp(problem: CheckProblem, path: Path) -> None:
    """The CalculiX input deck of ``problem``: C3D20R mesh, supports, pins, pressure, node print."""
    x, y, z = problem.axes()
    X, Y, Z = (np.sort(np.r_[a, 0.5 * (a[1:] + a[:-1])]) for a in (x, y, z))
    nx, ny, nz = len(X), len(Y), len(Z)

    def nid(i: int, j: int, k: int) -> int:
        return 1 + i + nx * (j + ny * k)

    keep = np.array(
        [[[(i % 2) + (j % 2) + (k % 2) <= 1 for k in range(nz)] for j in range(ny)] for i in range(nx)]
    )
    lines = ["*HEADING", "qpscale flexure check (formulations/membrane.md sec. 9b)", "*NODE"]
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                if keep[i, j, k]:
                    lines.append(f"{nid(i, j, k)}, {X[i]:.12g}, {Y[j]:.12g}, {Z[k]:.12g}")
    lines.append("*ELEMENT, TYPE=C3D20R, ELSET=EALL")
    (_, p_top, plate), (_, p_bot, sup) = _pressures(problem, y)
    top_el, bot_el = [], []
    e = 0
    for k in range(0, nz - 1, 2):
        for j in range(0, ny - 1, 2):
            for i in range(0, nx - 1, 2):
                e += 1
                nodes = [nid(i + a, j + b, k + c) for a, b, c in _C3D20]
                lines.append(f"{e}, " + ", ".join(map(str, nodes[:15])) + ",")
                lines.append(", ".join(map(str, nodes[15:])))
                if k == nz - 3 and j // 2 in plate:
                    top_el.append(e)
                if k == 0 and j // 2 in sup:
                    bot_el.append(e)
    jl = [int(np.argmin(np.abs(Y - s))) for s in (0.0, -problem.span / 2, problem.span / 2)]
    mid = [nid(i, j, 0) for j in jl for i in range(nx)]
    ids = [
        nid(int(np.argmin(np.abs(X - a))), int(np.argmin(np.abs(Y - b))), 0)
        for a, b in ((0.0, 0.0), (2.5, 0.0), (0.0, 2.5))
    ]
    lines += _nset("MID", mid) + _elset("TOP", top_el) + _elset("BOT", bot_el)
    lines += [
        "*MATERIAL, NAME=M",
        "*ELASTIC",
        f"1.0, {problem.nu:.12g}",
        "*SOLID SECTION, ELSET=EALL, MATERIAL=M",
        "*STEP",
        "*STATIC",
        "*BOUNDARY",
        f"{ids[0]}, 1, 3, 0.0",
        f"{ids[1]}, 2, 3, 0.0",
        f"{ids[2]}, 3, 3, 0.0",
        "*DLOAD",  # a positive pressure pushes into the face: down on the top (P2), up on the bottom (P1)
        f"TOP, P2, {-p_top:.12g}",
        f"BOT, P1, {p_bot:.12g}",
        "*NODE PRINT, NSET=MID",
        "U",
        "*END STEP",
    ]
    path.write_text("\n".join(lines) + "\n")
    path.with_suffix(".mid").write_text(
        "\n".join(" ".join(f"{nid(i, j, 0)}:{X[i]:.12g}" for i in range(nx)) for j in jl)
    )


def _nset(name: str, ids: list[int]) -> list[str]:
    return [f"*NSET, NSET={name}"] + [", ".join(map(str, ids[i : i + 16])) for i in range(0, len(ids), 16)]


def _elset(name: str, ids: list[int]) -> list[str]:
    return [f"*ELSET, ELSET={name}"] + [", ".join(map(str, ids[i : i + 16])) for i in range(0, len(ids), 16)]


def ccx_deflection(problem: CheckProblem, workdir: Path | None = None, ccx: str = "ccx") -> float:
    """D* of ``problem`` by CalculiX: write the deck, run ``ccx``, read the mid-line's u_z from the .dat.

    Raises
    ------
    SolverUnavailable
        ``ccx`` is not on the path.
    SolverFailure
        ``ccx`` failed or printed no displacements.
    """
    exe = shutil.which(ccx)
    if exe is None:
        raise SolverUnavailable(f"CalculiX executable {ccx!r} not found")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(workdir or tmp)
        work.mkdir(parents=True, exist_ok=True)
        inp = work / "check.inp"
        write_inp(problem, inp)
        run = subprocess.run([exe, "-i", "check"], cwd=work, capture_output=True, text=True, timeout=3600)
        dat = work / "check.dat"
        if run.returncode != 0 or not dat.exists():
            raise SolverFailure("ccx", f"exit {run.returncode}", detail=run.stdout[-500:] + run.stderr[-500:])
        u = _read_dat(dat.read_text())
        rows = [
            [t.split(":") for t in row.split()] for row in inp.with_suffix(".mid").read_text().splitlines()
        ]
    if not all(int(n) in u for row in rows for n, _ in row):
        raise SolverFailure("ccx", "missing displacements", detail=str(len(u)))
    means = [
        _line_mean(np.array([float(x) for _, x in row]), np.array([u[int(n)] for n, _ in row]), True)
        for row in rows
    ]
    return -(means[0] - 0.5 * (means[1] + means[2])) * problem.I_m


def _read_dat(text: str) -> dict[int, float]:
    """u_z of every node printed in a ccx .dat displacement block."""
    out = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) == 4 and re.fullmatch(r"\d+", parts[0]):
            out[int(parts[0])] = float(parts[3])
    return out


def qpscale_extrapolated(nu: float, h: float = 0.5, nz: int = 4) -> tuple[float, float, dict]:
    """D* of qpscale's membrane extrapolated to the converged limit, and its error estimate.

    In-plane refinement (h, h/2, h/4 at ``nz`` layers) and through-thickness refinement (nz, 2 nz,
    4 nz at ``h``) move D* in opposite directions (membrane.md sec. 9), so each direction is
    extrapolated on its own (``richardson``) and the two corrections are added to D*(h, nz).
    Returns the limit, the summed error estimates and the values by (h, nz).
    """
    runs = {(h / 2**k, nz): qpscale_deflection(CheckProblem(nu=nu, h=h / 2**k, nz=nz)) for k in range(3)}
    runs.update({(h, nz * 2**k): qpscale_deflection(CheckProblem(nu=nu, h=h, nz=nz * 2**k)) for k in (1, 2)})
    base = runs[(h, nz)]
    lim_h, _, err_h = richardson([runs[(h / 2**k, nz)] for k in range(3)])
    lim_z, _, err_z = richardson([runs[(h, nz * 2**k)] for k in range(3)])
    return base + (lim_h - base) + (lim_z - base), err_h + err_z, runs

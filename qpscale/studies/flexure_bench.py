"""Flexure on a ladder of meshes: time against accuracy, and C_f* extrapolated with an error estimate.

Implements formulations/membrane.md sec. 9. The membrane's discretisation error has three sources
that move C_f* by different amounts and, for two of them, in opposite directions: the in-plane
element size ``h`` (refining raises C_f*), the layers through the thickness ``nz`` (refining lowers
it) and the element size at the rollers and plate edges ``contact_h`` (the contact width under a
roller).  Each is refined on its own from a base mesh, three levels by a constant ratio, and
extrapolated by Richardson; the corrections are added to the base value and their error estimates
summed.  ``flexure_bench`` is the table ``qpscale bench`` can print: per mesh, C_f*, wall time and
the error against that extrapolated limit.  Covered membranes converge under the companion
refinement of sec. 9c (layers and elements across each gap doubled together, ``companion_ladder``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..experiments.flexure import FlexureSetup, run_flexure
from ..tiling import Design


@dataclass(frozen=True)
class MeshLevel:
    """One flexure mesh: in-plane size ``h`` (L), ``nz`` layers, ``contact_h`` at rollers/plate (L)
    and ``gap_elements`` across each gap between scales (membrane.md sec. 9c)."""

    h: float
    nz: int
    contact_h: float
    gap_elements: int | None = 2

    def apply(self, setup: FlexureSetup) -> FlexureSetup:
        mem = replace(setup.membrane, h=self.h, nz=self.nz)
        return replace(setup, membrane=mem, contact_h=self.contact_h, gap_elements=self.gap_elements)

    def refined(self) -> MeshLevel:
        """The companion of the error estimate (``experiments.flexure.refined``)."""
        n = None if self.gap_elements is None else 2 * self.gap_elements
        return MeshLevel(self.h, 2 * self.nz, self.contact_h / 2, n)


#: The default mesh of ``qpscale flexure`` and the paper study (membrane.md secs. 9, 9c).
DEFAULT_LEVEL = MeshLevel(0.5, 3, 0.05)

#: The bare membrane's converged C_f* and its error estimate (nu 0.4999, rollers r = 0.5 L), from
#: ``converged_compliance(FlexureSetup(mode="bare", increments=1))`` (membrane.md sec. 9; recomputed
#: by the slow test of tests/test_flexure_bench.py and by the full ``qpscale bench``).  The quick bench
#: measures its meshes against it instead of recomputing it (2-3 minutes).
BARE_LIMIT = (9.67, 0.07)

#: The covered membrane of the flexure bench: the square staggered array, load line x (sec. 9c).
SCALED_BENCH = FlexureSetup(design=Design(shape="square", tiling="staggered"), load_line="x")


def richardson(values: list[float], ratio: float = 2.0) -> tuple[float, float, float]:
    """Limit, observed order and error estimate of the finest of three values refined by ``ratio``.

    ``values`` go from coarse to fine. Order ``p = log(|v1 - v0| / |v2 - v1|) / log(ratio)``, limit
    ``v2 + (v2 - v1) / (ratio^p - 1)``, error estimate ``|limit - v2|``.  Outside the asymptotic
    range (the differences change sign or do not shrink) the order is NaN, the limit is ``v2`` and the
    error estimate is the larger difference: a bound, not an extrapolation.
    """
    v0, v1, v2 = values[-3:]
    d0, d1 = v1 - v0, v2 - v1
    if d1 == 0.0:
        return float(v2), float("inf"), 0.0
    if d0 * d1 <= 0 or abs(d1) >= abs(d0):
        return float(v2), float("nan"), float(max(abs(d0), abs(d1)))
    p = float(np.log(abs(d0) / abs(d1)) / np.log(ratio))
    limit = v2 + d1 / (ratio**p - 1.0)
    return float(limit), p, float(abs(limit - v2))


@dataclass(frozen=True)
class ConvergedCompliance:
    """C_f* extrapolated from ``base`` along each refinement direction (``richardson``).

    Attributes
    ----------
    Cf_star : float
        Base value plus the three corrections.
    error : float
        Sum of the three Richardson error estimates.
    base : float
        C_f* on the base mesh.
    directions : dict
        Per direction (``"h"``, ``"nz"``, ``"contact_h"``): the three values, the observed order and
        the error estimate.
    runs : list of dict
        Every curve: mesh, C_f*, wall time, retained DOFs.
    """

    Cf_star: float
    error: float
    base: float
    directions: dict
    runs: list


def run_level(setup: FlexureSetup, level: MeshLevel) -> dict:
    """One curve on ``level``: the mesh, C_f*, wall time (s) and retained DOFs."""
    r = run_flexure(level.apply(setup))
    return {
        "h": level.h,
        "nz": level.nz,
        "contact_h": level.contact_h,
        "gap_elements": level.gap_elements if setup.mode != "bare" else None,
        "Cf_star": r.Cf_star,
        "wall_s": r.wall_s,
        "n_retained": r.n_retained,
    }


def ladder(base: MeshLevel, ratio: float = 2.0) -> dict[str, list[MeshLevel]]:
    """The three-level sequence of each refinement direction from ``base``."""
    r = ratio
    return {
        "h": [replace(base, h=base.h / r**k) for k in range(3)],
        "nz": [replace(base, nz=int(round(base.nz * r**k))) for k in range(3)],
        "contact_h": [replace(base, contact_h=base.contact_h / r**k) for k in range(3)],
    }


def converged_compliance(
    setup: FlexureSetup, base: MeshLevel = DEFAULT_LEVEL, ratio: float = 2.0, skip: tuple[str, ...] = ()
) -> ConvergedCompliance:
    """C_f* of ``setup`` extrapolated along each refinement direction from ``base``, with an error estimate.

    ``skip`` leaves directions out (their correction and error count as zero; e.g. ``contact_h`` for
    a scaled membrane, whose rollers carry a wide contact).
    """
    runs: dict[MeshLevel, dict] = {}
    directions: dict[str, dict] = {}
    for name, levels in ladder(base, ratio).items():
        if name in skip:
            continue
        for lv in levels:
            if lv not in runs:
                runs[lv] = run_level(setup, lv)
        values = [runs[lv]["Cf_star"] for lv in levels]
        limit, p, err = richardson(values, ratio)
        directions[name] = {"values": values, "order": p, "limit": limit, "error": err}
    v0 = runs[base]["Cf_star"]
    limit = v0 + sum(float(d["limit"]) - v0 for d in directions.values())
    error = sum(float(d["error"]) for d in directions.values())
    return ConvergedCompliance(limit, error, v0, directions, list(runs.values()))


def companion_ladder(base: MeshLevel = DEFAULT_LEVEL, levels: int = 3) -> list[MeshLevel]:
    """``base`` and its companions refined ``levels - 1`` times (sec. 9c: layers, elements across each
    gap and the contact size, all by 2)."""
    out = [base]
    for _ in range(levels - 1):
        out.append(out[-1].refined())
    return out


def flexure_bench(
    setup: FlexureSetup, levels: list[MeshLevel], reference: ConvergedCompliance | float
) -> list[dict]:
    """Time against accuracy: per mesh, C_f*, wall time and the relative error against ``reference``
    (a converged compliance, or its value)."""
    limit = reference.Cf_star if isinstance(reference, ConvergedCompliance) else float(reference)
    rows = []
    for lv in levels:
        row = run_level(setup, lv)
        row["rel_error"] = abs(row["Cf_star"] - limit) / limit
        rows.append(row)
    return rows


def companion_bench(setup: FlexureSetup, base: MeshLevel = DEFAULT_LEVEL) -> tuple[list[dict], tuple]:
    """Time against accuracy along the companion ladder of ``base`` (three meshes): each row's error
    against the ladder's Richardson limit, which is returned with its order and error estimate."""
    rows = [run_level(setup, lv) for lv in companion_ladder(base)]
    limit, p, err = richardson([r["Cf_star"] for r in rows])
    for r in rows:
        r["rel_error"] = abs(r["Cf_star"] - limit) / limit
    return rows, (limit, p, err)

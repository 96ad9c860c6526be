"""Small named cases with known answers, reused across the test modules."""

from __future__ import annotations

from qpscale import DESIGNS, Design

ALL_DESIGNS = [Design(shape=s, tiling=t) for s, t in DESIGNS]
GAPS = (0.0, 0.005, 0.05, 0.2)
SLANTS = ((0.0, 0.0), (60.0, 0.0), (60.0, 45.0), (60.0, 90.0), (63.4, 0.0))

# The paper's validation scene: 5x5 square array, d = 0.005 L, t = L.
PAPER_SQUARE = Design()


def work_balance(setup, result) -> tuple[float, float]:
    """The load's work along a puncture curve (trapezoidal) and what it must equal for
    frictionless contact that does not penetrate: the stored energy at failure plus the energy
    released at the located snaps (the step control keeps the quadrature error within 1e-3 of
    each step's work, formulations/puncture.md sec. 2)."""
    import numpy as np

    from qpscale.experiments.puncture import build_model

    _, K = build_model(setup)
    w, F = result.w_star, result.F_star
    work = float(np.sum(0.5 * np.diff(w) * (F[1:] + F[:-1])))
    q = result.states[-1].q.ravel()
    released = sum(e.energy_released for e in result.events if e.kind == "snap")
    return work, 0.5 * float(q @ (K @ q)) + released


def fuzz_setup(i: int):
    """The puncture set-up of design ``i`` of the bench's fuzz (seed 1000) as the fuzz runs it:
    contact interaction, its coupling and nu, its drawn vertex, four target increments."""
    from qpscale.experiments.puncture import PunctureSetup
    from qpscale.studies.bench_report import fuzz_design_number

    design, extra, point = fuzz_design_number(i)
    return PunctureSetup(
        design=design,
        interaction="contact",
        coupling=extra["coupling"],
        nu=extra["nu"],
        load_point=point,
        increments=4,
    )

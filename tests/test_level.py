"""A load level's outcome and its declared rescue policy (formulations/increment.md sec. 5).

Every rescue is made to fire by a fault-injecting backend: Clarabel wrapped so that chosen QPs
fail (no point, status ``injected fault``) or answer a little off (a near miss).  Each test checks
that the rescue fired (a typed ``Rescue`` event) and that the state it reaches is the state the
unperturbed level or path reaches, to the accuracy the sequential QP itself has.  The puncture
levels and the plate positions of flexure are solved by the same driver (``qpscale.level``), so
the level rescues are checked on both.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

import qpscale.active_set as active_set
import qpscale.continuation as continuation
import qpscale.level as level_module
import qpscale.solvers as solvers
from qpscale import Design
from qpscale.cli import app
from qpscale.errors import SolverFailure
from qpscale.events import LEVEL_RESCUES, PATH_RESCUES, Rescue
from qpscale.experiments import flexure
from qpscale.experiments.puncture import PunctureSetup, _load_point, build_model, run_puncture
from qpscale.increment import PunctureLevel, SQPSettings
from qpscale.level import LevelStatus
from qpscale.membrane import MembraneModel
from qpscale.qp import candidate_result

SMALL = Design(rings=1)
# The faults are injected into Clarabel (its statuses, its settings' names, its retry after any
# rejection), so every level and path here asks for it, whatever the default backend.
CLARABEL = SQPSettings(solver="clarabel")
EDGE = (1.0, 0.0)  # mid-edge of the 3x3 square's centre scale: a continuous path to a fold
DEPTH = 0.3  # the loaded scale presses on its neighbour there (planes in contact)


class Faults:
    """Clarabel with injected faults, counted per QP (a retry of the same QP is the same QP).

    ``fail``: indices (1-based) of QPs answered with no point; ``short``: QPs whose first answer is
    5e-9 off in x (residuals ~1e-8: a near miss of the 1e-9 check); ``noise``: every answer at
    the ordinary tolerance is the exact answer of the QP with its linear term moved by up to this
    much (it passes the 1e-9 check, and its dq carries noise of that size over K's smallest
    eigenvalue).  ``active`` off lifts every fault.
    """

    def __init__(
        self,
        fail: set[int] | None = None,
        short: set[int] | None = None,
        every: bool = False,
        noise: float = 0.0,
    ):
        self.fail, self.short, self.every, self.noise = fail or set(), short or set(), every, noise
        self.rng = np.random.default_rng(0)
        self.original = solvers._REGISTRY["clarabel"]
        # The QPs themselves, not their ids: an id is reused once its object is freed, and a new
        # QP taken for the last one shifted the count (a flaky halve_step test).
        self.seen: list[object] = []
        self.calls = 0
        self.active = True

    def __call__(self, qp, opts, ws):
        self.calls += 1
        if not self.seen or self.seen[-1] is not qp:
            self.seen.append(qp)
        k = len(self.seen)
        if self.active and (self.every or k in self.fail):
            return candidate_result(
                qp, None, None, None, status="injected fault", ok=False, build_s=0, solve_s=0
            )
        if self.active and self.noise and opts["tol_gap_abs"] >= 1e-11:
            moved = replace(qp, q=qp.q + self.rng.uniform(-self.noise, self.noise, qp.n))
            r = self.original(moved, opts, ws)
            return candidate_result(qp, r.x, r.z, r.y, status=r.status, ok=r.found, build_s=0, solve_s=0)
        r = self.original(qp, opts, ws)
        if self.active and k in self.short and "static_regularization_constant" not in opts:
            x = r.x + 5e-9
            return candidate_result(qp, x, r.z, r.y, status="AlmostSolved", ok=True, build_s=0, solve_s=0)
        return r


@pytest.fixture(scope="module")
def level():
    """The mid-edge level of the 3x3 square, solved without faults: (arguments, state)."""
    setup = PunctureSetup(design=SMALL, load_point=EDGE, probe=False, sqp=CLARABEL)
    patch, K = build_model(setup)
    args = (patch, K, np.zeros((patch.n_scales, 5)), _load_point(patch, EDGE), DEPTH, setup.contact)
    clean = PunctureLevel(*args, CLARABEL).solve()
    assert clean.converged and not clean.rescues and clean.state.contacts.planes.count > 0
    return args, clean.state


def _same_state(a, b):
    # The sequential QP stops at |dq| <= 1e-8, so two converged runs of one level differ by about
    # that much in q; F is a multiplier of the same accuracy.
    assert np.max(np.abs(a.q - b.q)) <= 1e-7
    assert a.F == pytest.approx(b.F, rel=1e-8)


def test_the_policy_is_declared_and_undeclared_rescues_are_refused():
    assert LEVEL_RESCUES == ("qp_retry", "stall_tighten", "other_plane_update")
    assert PATH_RESCUES == ("halve_step", "plain_iteration")
    with pytest.raises(ValueError, match="not declared"):
        Rescue("try_harder", 0.1)
    assert Rescue("qp_retry", 0.1, 3, "x").to_dict() == {
        "kind": "rescue",
        "rescue": "qp_retry",
        "delta": 0.1,
        "increment": 3,
        "detail": "x",
    }


def test_a_level_that_fails_reports_the_backends_status_and_no_state(level, monkeypatch):
    args, _ = level
    faults = Faults(every=True)
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", faults)
    out = PunctureLevel(*args, CLARABEL, increment=7).solve()
    assert out.status is LevelStatus.QP_FAILED and out.state is None
    assert out.failure.status == "injected fault" and out.failure.increment == 7
    # Both plane updates were tried, each QP once more by qp_retry (Clarabel after any rejection).
    assert faults.calls == 4
    assert [r.rescue for r in out.rescues] == ["qp_retry", "qp_retry"]
    with pytest.raises(SolverFailure, match="injected fault"):
        out.unwrap()


def test_a_path_whose_levels_fail_exits_3_with_the_status(monkeypatch):
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", Faults(every=True))
    args = ["puncture", "--rings", "1", "--no-probe", "--load-point", "1", "0", "--solver", "clarabel"]
    out = CliRunner().invoke(app, args)
    assert out.exit_code == 3 and "injected fault" in out.output


def test_qp_retry_fires_on_a_near_miss_and_keeps_the_state(level, monkeypatch):
    args, clean = level
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", Faults(short={2}))
    out = PunctureLevel(*args, CLARABEL).solve()
    assert out.converged and [r.rescue for r in out.rescues] == ["qp_retry"]
    assert "AlmostSolved" in out.rescues[0].detail
    _same_state(out.state, clean)


@pytest.mark.parametrize("faults", [{}, {"short": {2}}, {"fail": {2}}])
def test_a_levels_qp_count_is_the_backends_calls(level, monkeypatch, faults):
    # LevelOutcome.solves (the JSON's qp_solves, summed over a path) against the backend's own call
    # count: plain, with a retried QP (two calls), and with a failed first attempt and its retry
    # followed by the other plane update (every call of both attempts).
    args, _ = level
    counter = Faults(**faults)
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", counter)
    out = PunctureLevel(*args, CLARABEL).solve()
    assert out.converged and out.solves == counter.calls > 1


def test_other_plane_update_fires_when_the_first_attempt_fails_and_keeps_the_state(level, monkeypatch):
    args, clean = level
    faults = Faults(fail={2})  # the first attempt's second QP fails, and so does its retry
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", faults)
    out = PunctureLevel(*args, CLARABEL).solve()
    assert out.converged
    assert [r.rescue for r in out.rescues] == ["qp_retry", "other_plane_update"]
    assert out.rescues[-1].detail == "damped"
    # A converged state is a fixed point of both plane updates (increment.md sec. 4b).
    _same_state(out.state, clean)


def test_stall_tighten_fires_when_the_steps_stall_on_solver_noise_and_keeps_the_state(level, monkeypatch):
    # Answers accurate to 5e-10 (they pass the 1e-9 check) move dq by ~1e-9 at random: with a step
    # test of 1e-10 the level stalls on that noise, the noisy answers of its next QPs are made
    # exact by the sparse active-set solve (the backend still adds its noise), and it converges
    # to the state the ordinary level reaches.
    args, clean = level
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", Faults(noise=5e-10))
    out = PunctureLevel(*args, replace(CLARABEL, step_tol=1e-10)).solve()
    assert [r.rescue for r in out.rescues] == ["stall_tighten"]
    assert out.converged and out.state.tightened
    # The last QP's answer is exact: its KKT residuals, from the QP's data, are at rounding (the
    # noisy answers' are ~1e-10).
    assert max(out.state.residuals.values()) <= 1e-13
    _same_state(out.state, clean)


def test_stall_tighten_that_cannot_make_an_answer_exact_is_recorded_and_no_state_is_made_up(
    level, monkeypatch
):
    # The same stall with an exact solve that does not converge: the level goes on with the noisy
    # answers, records why, and ends "not converged" with its status (never a state).
    args, _ = level
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", Faults(noise=5e-10))

    def no_exact(qp, x0, z0, y0, **kw):
        return active_set.SparseSolution(x0, z0, y0, False, "outer iteration limit 20", 20, 0, 0)

    monkeypatch.setattr(active_set, "solve_sparse", no_exact)
    out = PunctureLevel(*args, replace(CLARABEL, step_tol=1e-10)).solve()
    details = [r.detail for r in out.rescues if r.rescue == "stall_tighten"]
    assert "exact solve not reached" in details
    assert not out.converged and out.state is None
    assert out.failure is not None and out.failure.status == "sequential QP did not converge"


def test_stall_tighten_ends_the_exact_answers_of_a_level_they_do_not_converge(level, monkeypatch):
    # An "exact" solve that hands the noisy answer back (it passes the residual check): the level
    # still stalls, so after STALL_WINDOW exact answers the stall is taken as no noise (a cycle of
    # the iteration, which exact answers repeat) and they end, recorded; the level fails with its
    # status.
    args, _ = level
    faults = Faults(noise=5e-10)
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", faults)
    exact_calls = []

    def echo(qp, x0, z0, y0, **kw):
        exact_calls.append(1)
        return active_set.SparseSolution(x0, z0, y0, True, "converged", 1, 1, 1)

    monkeypatch.setattr(active_set, "solve_sparse", echo)
    out = PunctureLevel(*args, replace(CLARABEL, step_tol=1e-10)).solve()
    details = [r.detail for r in out.rescues if r.rescue == "stall_tighten"]
    assert "not noise: exact answers ended" in details
    # Each attempt at the level (the first plane update, then the other) stalls once and makes
    # at most STALL_WINDOW answers exact.
    attempts = sum(1 for d in details if d.endswith("stalled"))
    assert 1 <= attempts and len(exact_calls) == attempts * level_module.STALL_WINDOW
    assert not out.converged and out.failure.status == "sequential QP did not converge"


@pytest.fixture(scope="module")
def plate():
    """The one-scale membrane (coarse) at the full plate travel, solved without faults: the model,
    the plate position and its state."""
    setup = flexure.FlexureSetup(
        mode="isolated", membrane=MembraneModel(h=1.0, nz=2), increments=1, solver="clarabel"
    )
    model = flexure.build_model(setup)
    clean = flexure.solve_position(model, np.zeros(len(model.cond.retained)), setup.max_deflection, 1, None)
    assert clean.converged and not clean.rescues
    return model, setup.max_deflection, clean.state


def _same_position(model, w, clean, **faults):
    """The position solved again under ``faults``: its outcome, and its state checked against the
    clean one.  The sequential QP stops at steps of 1e-9 L, each QP answered to 1e-9 (exactly once
    a stall made it so), so the states differ by ~1e-9 in z and the plate force by ~1e-9 of
    itself."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(solvers._REGISTRY, "clarabel", Faults(**faults))
        out = flexure.solve_position(model, np.zeros(len(model.cond.retained)), w, 1, None)
    assert out.converged
    assert np.max(np.abs(out.state.z - clean.z)) <= 1e-8 * np.max(np.abs(clean.z))
    assert out.state.force == pytest.approx(clean.force, rel=1e-8)
    return out


def test_a_flexure_position_that_fails_reports_the_status_and_the_curve_stops_with_it(plate, monkeypatch):
    model, w, _ = plate
    faults = Faults(every=True)
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", faults)
    out = flexure.solve_position(model, np.zeros(len(model.cond.retained)), w, 4, None)
    assert out.status is LevelStatus.QP_FAILED and out.state is None
    assert out.failure.status == "injected fault" and out.failure.increment == 4
    # The first QP once more by qp_retry (Clarabel after any rejection), then the position stops.
    assert faults.calls == 2 and [r.rescue for r in out.rescues] == ["qp_retry"]
    # The curve cannot go on: only there the failure is raised, and the command line exits 3.
    with pytest.raises(SolverFailure, match="injected fault"):
        flexure.run_model(model)
    cli = CliRunner().invoke(app, ["flexure", "--bare", "--mesh-h", "1", "--solver", "clarabel"])
    assert cli.exit_code == 3 and "injected fault" in cli.output


def test_flexure_qp_retry_fires_on_a_near_miss_and_keeps_the_state(plate):
    model, w, clean = plate
    out = _same_position(model, w, clean, short={2})
    assert [(r.rescue, r.delta, r.increment) for r in out.rescues] == [("qp_retry", w, 1)]
    assert "AlmostSolved" in out.rescues[0].detail


def test_flexure_stall_tighten_fires_on_solver_noise_and_keeps_the_state(plate):
    # Answers accurate to 5e-10 (they pass the 1e-9 check) move z by ~3e-9 at random through the
    # soft membrane, above the step test of 1e-9 L: the position stalls on that noise, the answers
    # of its next QPs are made exact and it converges to the clean state.
    model, w, clean = plate
    out = _same_position(model, w, clean, noise=5e-10)
    assert [r.rescue for r in out.rescues] == ["stall_tighten"]


def test_a_flexure_curve_records_the_rescues_of_its_positions(monkeypatch):
    setup = flexure.FlexureSetup(
        mode="isolated", membrane=MembraneModel(h=1.0, nz=2), increments=1, solver="clarabel"
    )
    clean = flexure.run_flexure(setup)
    assert clean.extras["rescues"] == []
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", Faults(short={2}))
    hurt = flexure.run_flexure(setup)
    assert [r.rescue for r in hurt.extras["rescues"]] == ["qp_retry"]
    assert hurt.Cf_star == pytest.approx(clean.Cf_star, rel=1e-8)


@pytest.fixture(scope="module")
def alone():
    """The isolated scale loaded at its corner (the path rescues act above the level, so no
    contact is needed), and its unperturbed path."""
    setup = PunctureSetup(design=Design(rings=0), load_point=(1.0, 1.0), probe=False, sqp=CLARABEL)
    return setup, run_puncture(setup)


def test_halve_step_fires_when_a_level_fails_and_the_path_keeps_Fc(alone, monkeypatch):
    setup, clean = alone
    # One QP of the first step's level fails, and so does its retry.  (QPs 1-3 are the probe's,
    # whose failure ends the path; QPs 7-10, the energy descent of the flagged first step.)
    faults = Faults(fail={5})
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", faults)
    hurt = run_puncture(setup)
    halved = [e for e in hurt.events if e.kind == "rescue" and e.rescue == "halve_step"]
    assert len(halved) == 1 and halved[0].detail == "injected fault"
    # F_c is located at phi_c whatever the steps (puncture.md sec. 3: to 1e-6 or better).
    assert hurt.Fc_star == pytest.approx(clean.Fc_star, rel=1e-6)


def test_the_failure_search_halves_a_cut_whose_level_fails_and_keeps_Fc(alone, monkeypatch):
    setup, clean = alone
    # Find the failure search's first QP on the unperturbed path, then fail it (and its retry).
    faults = Faults()
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", faults)
    first: list[int] = []
    original = continuation.Path.locate_failure

    def locate(self, lo, hi, index):
        first.append(len(faults.seen) + 1)
        return original(self, lo, hi, index)

    monkeypatch.setattr(continuation.Path, "locate_failure", locate)
    again = run_puncture(setup)
    assert again.Fc_star == pytest.approx(clean.Fc_star, rel=1e-12) and len(first) == 1
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", Faults(fail={first[0]}))
    hurt = run_puncture(setup)
    halved = [e for e in hurt.events if e.kind == "rescue" and e.rescue == "halve_step"]
    assert len(halved) == 1 and halved[0].detail == "injected fault"
    # The cut's level failed, the halved cut converged, and the search went on to phi_c: F_c is
    # located to the search's tolerance (puncture.md sec. 3, 1e-6 or better).
    assert hurt.Fc_star == pytest.approx(clean.Fc_star, rel=1e-6)


def test_plain_iteration_fires_when_no_step_converges_and_the_path_keeps_Fc(alone, monkeypatch):
    setup, clean = alone
    faults = Faults(every=True)
    faults.active = False
    original = PunctureLevel.solve
    levels = {"n": 0}

    def level_with_faults(self):
        # From the fifth level on, every extrapolated iteration fails until the path falls back
        # on the plain iteration (anderson_depth = 0), which the faults spare.
        levels["n"] += 1
        faults.active = levels["n"] >= 5 and self.settings.anderson_depth > 0 and not fired()
        return original(self)

    def fired():
        return any(getattr(e, "rescue", "") == "plain_iteration" for e in events)

    events: list = []
    monkeypatch.setitem(solvers._REGISTRY, "clarabel", faults)
    monkeypatch.setattr(PunctureLevel, "solve", level_with_faults)
    original_run = continuation.Path.run

    def run(self, *a, **kw):
        nonlocal events
        events = self.events
        return original_run(self, *a, **kw)

    monkeypatch.setattr(continuation.Path, "run", run)
    hurt = run_puncture(setup)
    kinds = [e.rescue for e in hurt.events if e.kind == "rescue"]
    assert kinds.count("plain_iteration") == 1 and kinds.count("halve_step") >= 10
    assert hurt.Fc_star == pytest.approx(clean.Fc_star, rel=1e-6)


def test_a_converged_step_is_confirmed_by_the_next_linearisation():
    # A step within the test whose rows moved (a plane swung about its hinge: the next
    # linearisation steps 1e-4) is no fixed point; the level goes on until two steps in a row are
    # within the test, and reports the second one's answer (formulations/increment.md sec. 4a).
    from qpscale.level import LevelControls, Step, solve

    class Swinging:
        controls = LevelControls(
            "fake", 0.1, 0, step_tol=1e-8, penetration_tol=1e-9, max_iter=20, anderson_depth=0
        )

        def __init__(self, sizes):
            self.sizes, self.calls = list(sizes), 0

        def linearise(self, x, rows, refresh):
            return x

        def solve(self, lin, tightened):
            size = self.sizes[min(self.calls, len(self.sizes) - 1)]
            self.calls += 1
            return Step(answer=self.calls, dx=np.full(2, size), labels=0)

        def penetration(self, x):
            return 0.0

        def state(self, x, answer, progress):
            return answer

    swinging = Swinging([1e-3, 1e-10, 1e-4, 1e-10, 1e-10, 1e-4])
    outcome = solve(swinging, np.zeros(2))
    assert outcome.converged and outcome.state == 5 and swinging.calls == 5
    settled = Swinging([1e-3, 1e-10, 1e-10, 1e-4])
    assert solve(settled, np.zeros(2)).state == 3


def test_relaxation_turns_an_expanding_oscillation_into_convergence():
    # The plain map x + f(x), f = (M - I)(x - x*), with multipliers mu = -1.4 and 0.3: mu < -1
    # makes the plain iteration oscillate with growing amplitude; the relaxed one (increment.md
    # sec. 4c) reaches the fixed point x*, an analytic value, and keeps omega = 1 on a contraction.
    from qpscale.level import MIN_RELAXATION, relaxation

    Q = np.array([[0.8, -0.6], [0.6, 0.8]])
    M = Q @ np.diag([-1.4, 0.3]) @ Q.T
    x_star = np.array([0.3, -0.2])

    def iterate(relax: bool) -> tuple[np.ndarray, float]:
        x, omega, last = np.zeros(2), 1.0, np.zeros(0)
        for _ in range(60):
            f = (M - np.eye(2)) @ (x - x_star)
            if relax:
                omega, last = relaxation(omega, f, last), f
            x = x + omega * f
        return x, omega

    plain, _ = iterate(False)
    relaxed, omega = iterate(True)
    assert np.linalg.norm(plain - x_star) > 1e3  # 1.4^60
    assert np.linalg.norm(relaxed - x_star) < 1e-12
    assert MIN_RELAXATION <= omega < 2.0 / (1.0 + 1.4)
    assert relaxation(1.0, 0.7 * np.ones(3), np.ones(3)) == 1.0


def test_the_plain_iteration_extrapolates_a_straight_drift_to_the_fixed_point(monkeypatch):
    # The plain map x + f(x), f = (M - I)(x - x*), with a slow mode (multiplier 0.998, the plain
    # iteration near a fold) and a contracting one (0.3): the steps are parallel, each 0.998 of the
    # last, and the plain iteration needs ln(1e-12 / 2.4e-4) / ln(0.998) = 9,650 of them to reach
    # the test.  Extrapolated along the drift (increment.md sec. 4c) it reaches the fixed point x*,
    # an analytic value, within the level's budget of 3,000 (measured 1,817: each doubling of the
    # step also amplifies the fast mode, whose growth ends the run of parallel steps); without the
    # extrapolation (DRIFT_MAX = 1) it does not.  Tolerance: the test |f| <= 1e-12 puts x within
    # 1e-12 / (1 - 0.998) = 5e-10 of x* along the slow mode (measured 6e-10 in the norm).
    import qpscale.level as level_module
    from qpscale.level import LevelControls, Step, solve

    Q = np.array([[0.8, -0.6], [0.6, 0.8]])
    M = Q @ np.diag([0.998, 0.3]) @ Q.T
    x_star = np.array([0.3, -0.2])

    class Drifting:
        controls = LevelControls(
            "fake", 0.1, 0, step_tol=1e-12, penetration_tol=1e-9, max_iter=3000, anderson_depth=0
        )

        def __init__(self):
            self.calls = 0

        def linearise(self, x, rows, refresh):
            return x

        def solve(self, x, tightened):
            self.calls += 1
            return Step(answer=np.array(x), dx=(M - np.eye(2)) @ (x - x_star), labels=0)

        def penetration(self, x):
            return 0.0

        def state(self, x, answer, progress):
            return x

    drifting = Drifting()
    outcome = solve(drifting, np.zeros(2))
    assert outcome.converged and np.linalg.norm(outcome.state - x_star) < 1e-9
    assert drifting.calls < 2500
    monkeypatch.setattr(level_module, "DRIFT_MAX", 1.0)
    assert not solve(Drifting(), np.zeros(2)).converged


def test_a_level_whose_plain_iteration_oscillated_reaches_phi_c():
    # Fuzz design 728 (seed 1000): just before a snap, the plain iteration's steps alternated in
    # sign and grew by 1.3 per linearisation, and the path failed with "sequential QP did not
    # converge" after 3000 of them.  Relaxed, it converges.  Independent checks: F_c against the
    # exact active-set solution of its QP (certify), and the conservation of work (the load's work
    # equals the stored energy plus the energy released at located snaps, 2e-3 as the step
    # control's quadrature allows).
    from .cases import fuzz_setup, work_balance

    setup = fuzz_setup(728)  # a 3x3 hexagon array slanted 42 deg towards 90 deg
    result = run_puncture(setup)
    assert result.tilt_deg[-1] == pytest.approx(13.0, rel=1e-6)
    assert result.Fc_check is not None and result.Fc_check.status == "verified"
    work, balance = work_balance(setup, result)
    assert work == pytest.approx(balance, rel=2e-3)

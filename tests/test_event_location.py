"""Event location on a path: the regula-falsi cut of a stability bracket (puncture.md sec. 4)."""

import numpy as np
import pytest

from qpscale.continuation import _split


def test_split_is_the_root_of_a_linear_eigenvalue():
    # mu + tol linear in depth: 0.3 at the last state, -0.1 at the ceiling 2.0 L above -> root at 1.5 L.
    assert _split(2.0, 0.3, -0.1) == pytest.approx(1.5, rel=1e-15)


@pytest.mark.parametrize("g_lo, g_hi", [(None, -0.1), (0.3, None), (-0.2, -0.1), (0.3, 0.1)])
def test_split_halves_without_a_sign_change(g_lo, g_hi):
    # A jump's bracket (no eigenvalue) or margins that do not bracket a root: plain bisection.
    assert _split(2.0, g_lo, g_hi) == 1.0


def test_split_stays_inside_the_bracket():
    # A root at the very end of the bracket is cut 1 % inside it, so each cut shrinks the bracket.
    assert _split(1.0, 1e-12, -1.0) == pytest.approx(0.01)
    assert _split(1.0, 1.0, -1e-12) == pytest.approx(0.99)
    assert np.isfinite(_split(1.0, 1e300, -1e-300))


# The predictor and the bracket's start (puncture.md sec. 2, Step size; sec. 3).


def _state(delta, q):
    from qpscale.increment import Equilibrium

    return Equilibrium(np.atleast_2d(np.asarray(q, dtype=float)), delta, 0.0, None, np.zeros(0), 1, 0.0)


def _line(delta):
    # A branch linear in the depth: the secant extrapolates it exactly.
    return _state(delta, [[1.0 + 2.0 * delta, -3.0 * delta, 0.5, 0.1 * delta, 0.0]])


def test_the_secant_predictor_is_exact_on_a_straight_branch():
    from qpscale.continuation import predict

    states = [_line(0.0), _line(0.1), _line(0.2)]
    guess = predict(states, 0.4)
    np.testing.assert_allclose(guess.q, _line(0.4).q, rtol=0, atol=1e-15)
    assert guess.delta == 0.4


def test_the_predictor_takes_a_base_of_at_least_half_the_step():
    from qpscale.continuation import PREDICTOR_REACH, predict

    # The last two states 6e-8 L apart (a resolved bracket), the error of each 1e-8: their secant
    # over a step of 0.03 would extrapolate that error by 5e5.  The nearest base of at least
    # step / PREDICTOR_REACH is taken instead, which is exact here despite the error.
    noisy = _state(0.2 + 6e-8, _line(0.2 + 6e-8).q + 1e-8)
    states = [_line(0.0), _line(0.1), _line(0.2), noisy]
    guess = predict(states, 0.23)
    assert PREDICTOR_REACH * (noisy.delta - 0.2) < 0.03 <= PREDICTOR_REACH * (noisy.delta - 0.1)
    np.testing.assert_allclose(guess.q, _line(0.23).q, rtol=0, atol=1e-8 * (1 + 0.03 / 0.1) + 1e-15)
    # With no such base the level starts from the last state.
    assert predict(states[-2:], 0.23) is noisy


def test_the_predictor_does_not_extrapolate_across_a_landing():
    from qpscale.continuation import predict

    # A jump's landing at the depth of the state before it, on another branch: the stretch from
    # the landing on (``since``) has one state, so the level starts from it.
    landing = _state(0.2, [[5.0, 5.0, 5.0, 5.0, 5.0]])
    states = [_line(0.0), _line(0.1), _line(0.2), landing]
    assert predict(states, 0.3, since=3) is landing
    after = _state(0.25, landing.q + 0.5)
    guess = predict([*states, after], 0.3, since=3)
    np.testing.assert_allclose(guess.q, landing.q + 1.0, rtol=0, atol=1e-14)


def test_a_level_inside_a_bracket_starts_between_its_two_states():
    from qpscale.continuation import _between

    a, b = _line(0.1), _line(0.3)
    start = _between(a, b, 0.25)
    np.testing.assert_allclose(start.q, _line(0.25).q, rtol=0, atol=1e-15)
    assert start.delta == 0.25 and start.contacts is a.contacts


def test_a_jump_is_located_coarsely_unless_it_is_the_failure():
    from qpscale.continuation import JUMP_RESOLUTION, SNAP_RESOLUTION, _resolution

    assert _resolution("snap", fine=False) == JUMP_RESOLUTION
    assert _resolution("snap", fine=True) == SNAP_RESOLUTION
    assert _resolution("unstable", fine=False) == JUMP_RESOLUTION
    assert _resolution("unstable", fine=True) == SNAP_RESOLUTION
    assert _resolution("unstable", fine=False, held=True) == SNAP_RESOLUTION
    assert _resolution("snap", fine=False, held=True) == JUMP_RESOLUTION
    assert _resolution("failed", fine=False) == SNAP_RESOLUTION
    assert SNAP_RESOLUTION < JUMP_RESOLUTION


def _unstable_path(delta_0, branch_tilt):
    """A path whose states lose stability at ``delta_0``, their smallest eigenvalue jumping from
    +1 to -1 there (as on hinged planes: the dart slanted towards 45 deg, puncture.md sec. 4), so
    that regula falsi bisects; and whose branch, reached by a push along the mode (the fifth DOF),
    holds 0.01 less energy and is tilted ``branch_tilt`` (rad) more.  F = delta and E = delta^2 / 2
    on the first branch, so its energy balance is exact and only the eigenvalue flags a state; the
    tilt grows as delta / 10."""
    from qpscale.continuation import Path, PathSettings, StateFunctions
    from qpscale.increment import Equilibrium
    from qpscale.level import LevelOutcome, LevelStatus
    from qpscale.stability import Stability

    mode = np.array([[0.0, 0.0, 0.0, 0.0, 1.0]])

    def state(delta, branched):
        q = np.array([[delta, 0.0, 0.0, 0.0, 1.0 if branched else 0.0]])
        return Equilibrium(q, delta, delta, None, np.zeros(0), 1, 0.0)

    def level(start, delta, index, descent=False):
        return LevelOutcome(LevelStatus.CONVERGED, state(delta, start.q[0, 4] != 0.0))

    def stability(eq):
        g = 1.0 if eq.q[0, 4] or eq.delta < delta_0 else -1.0
        return Stability(g, g > 0.0, mode, 0)

    functions = StateFunctions(
        energy=lambda eq: 0.5 * eq.delta**2 - 0.01 * eq.q[0, 4],
        force_norm=lambda eq: 1e-3,
        tilt=lambda eq: eq.delta / 10.0 + (branch_tilt if eq.q[0, 4] else 0.0),
        stability=stability,
    )
    settings = PathSettings(phi_c_deg=13.0, increments=16, max_increments=400, solver="test", check=True)
    return Path(level, functions, settings, state(0.0, False))


@pytest.mark.parametrize("failure", [False, True])
def test_a_loss_of_stability_is_located_coarsely_unless_it_is_the_failure(failure):
    # Off a held path a loss of stability whose branch lands below phi_c is located to
    # JUMP_RESOLUTION of its depth, like a jump (where it lies within that bracket changes only the
    # start of the landing); one whose landing passes phi_c is the failure, and its bracket is
    # refined to SNAP_RESOLUTION before the branch is recorded, once.
    from qpscale.continuation import JUMP_RESOLUTION, SNAP_RESOLUTION, Branch, Failure

    delta_0 = 0.41
    path = _unstable_path(delta_0, branch_tilt=0.5 if failure else 0.01)
    states = path.run(step=0.05)
    branches = [e for e in path.events if isinstance(e, Branch)]
    assert len(branches) == 1
    at = branches[0].delta
    resolution = SNAP_RESOLUTION if failure else JUMP_RESOLUTION
    assert delta_0 <= at <= delta_0 * (1.0 + resolution)
    below = max(s.delta for s in states if s.delta < delta_0)
    assert at - below <= resolution * at
    if failure:
        assert isinstance(path.events[-1], Failure)
        assert states[-1].delta == below
    else:
        assert at - below > SNAP_RESOLUTION * at  # not refined further than it needs


def test_a_push_that_comes_back_within_the_energies_resolution_is_no_branch():
    # An unstable state pushed along its mode whose plain iteration returns to it (fuzz design
    # 140: energy 6.8e-13 lower, against a resolution of 8.6e-7) is not confirmed; a landing whose
    # energy is lower by more than the resolution is.  K = I: energy 1/2 |q|^2, |K q|_1 = |q|_1.
    from qpscale.continuation import STATE_ERROR, Path, PathSettings, StateFunctions
    from qpscale.increment import STEP_TOL
    from qpscale.level import LevelOutcome, LevelStatus
    from qpscale.stability import Stability

    eq = _state(0.5, [[1.0, 0.0, 0.0, 0.0, 0.0]])
    resolution = 2 * STATE_ERROR * STEP_TOL * 1.0

    def path_landing_at(energy_drop):
        landed = _state(0.5, [[np.sqrt(1.0 - 2.0 * energy_drop), 0.0, 0.0, 0.0, 0.0]])
        functions = StateFunctions(
            energy=lambda s: 0.5 * float(np.sum(s.q**2)),
            force_norm=lambda s: float(np.abs(s.q).sum()),
            tilt=lambda s: 0.0,
            stability=lambda s: None,
        )
        settings = PathSettings(phi_c_deg=13.0, increments=16, max_increments=400, solver="test")
        level = lambda start, delta, index, descent=False: LevelOutcome(LevelStatus.CONVERGED, landed)  # noqa: E731
        return Path(level, functions, settings, eq)

    sv = Stability(-1e-3, False, np.zeros((1, 5)), 0)
    for drop, confirmed in ((1e-12, False), (0.5 * resolution, False), (10 * resolution, True)):
        path = path_landing_at(drop)
        landing = path.branch_off(eq, sv, sides=(1.0, -1.0))
        assert (landing is not eq) is confirmed, drop
    # A held path's bifurcation takes its one chosen side whenever it lowers the energy at all.
    assert path_landing_at(1e-12).branch_off(eq, sv, sides=(1.0,), resolved=False) is not eq


@pytest.mark.parametrize("lo_gap, width, located", [(1e-7, 1e-12, True), (1e-4, 1e-13, False)])
def test_a_failure_search_whose_bracket_closes_to_one_depth_ends_without_a_nan_start(lo_gap, width, located):
    # The failure search (puncture.md sec. 3) cuts its bracket where regula falsi puts the root;
    # with the upper state far past phi_c the cut rounds to the lower state's own depth, and a
    # level there that lands on the other side (another basin) leaves two states of one depth.
    # Interpolating between them divided by a zero width: a NaN start (the 5x5 dart slanted
    # 60 deg towards 45 deg failed so, as an invalid input).  Now the round-off rule decides:
    # the lower state if it lies within TILT_LOCATED of phi_c, else the search fails by status.
    from qpscale.continuation import TILT_LOCATED, Path, PathSettings, StateFunctions
    from qpscale.errors import SolverFailure
    from qpscale.level import LevelOutcome, LevelStatus

    settings = PathSettings(phi_c_deg=13.0, increments=16, max_increments=400, solver="test")
    phi_c = np.deg2rad(settings.phi_c_deg)
    lo = _state(1.0, [[0.0, 0.0, 0.0, phi_c * (1.0 - lo_gap), 0.0]])
    hi = _state(1.0 + width, [[0.0, 0.0, 0.0, 1.5 * phi_c, 0.0]])
    starts = []

    def level(start, delta, index, descent=False):
        starts.append(start.q.copy())
        return LevelOutcome(LevelStatus.CONVERGED, _state(delta, hi.q))

    functions = StateFunctions(
        energy=lambda s: 0.0,
        force_norm=lambda s: 0.0,
        tilt=lambda s: float(s.q[0, 3]),
        stability=lambda s: None,
    )
    path = Path(level, functions, settings, lo)
    if located:
        assert lo_gap <= TILT_LOCATED
        assert path.locate_failure(lo, hi, 7) is lo
    else:
        with pytest.raises(SolverFailure, match="failure tilt not located"):
            path.locate_failure(lo, hi, 7)
    assert starts and all(np.isfinite(q).all() for q in starts)

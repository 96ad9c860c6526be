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

"""Linear modes' conventions: a sign per mode that rounding cannot flip."""

import numpy as np

from latentsim.solve.modes import fix_sign


def test_fix_sign_makes_the_largest_entry_positive():
    V = np.array([[0.1, -0.2], [-0.9, 0.5], [0.3, 0.1]])
    W = fix_sign(V)
    assert np.array_equal(W, V * np.array([-1.0, 1.0]))
    assert np.array_equal(fix_sign(-V), W)  # eigenvectors have no sign: both give the same


def test_fix_sign_ignores_rounding_between_tied_entries():
    """A half-turn-symmetric mode has entries of equal size and opposite sign; which of the two is
    larger by one ulp must not decide the sign."""
    a = 0.5
    up = np.array([[a * (1 + 4e-16)], [0.1], [-a]])
    down = np.array([[a], [0.1], [-a * (1 + 4e-16)]])
    assert fix_sign(up)[0, 0] > 0 and fix_sign(down)[0, 0] > 0  # the first of the tied entries decides
    assert fix_sign(-up)[0, 0] > 0 and fix_sign(-down)[0, 0] > 0
    # a real difference is not a tie
    far = np.array([[a], [0.1], [-1.01 * a]])
    assert fix_sign(far)[2, 0] > 0

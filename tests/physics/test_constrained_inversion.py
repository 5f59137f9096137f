"""The Neural Modes ground truth's constrained Newton keeps tetrahedra from inverting (latentsim.solve.constrained).

- ``first_inversion``: the first root in (0, 1] of det D(x + t dx) over the positive elements, against a
  dense sampling of t; inf where the step inverts none; elements inverted at x are not watched.
- On a clamped stvk_nm beam at modal amplitudes where the exact-Hessian KKT steps turn elements inside
  out (StVK has E = 0 for a reflected element) and end unconverged at the iteration cap, the guarded
  iteration converges to the tolerance with every element positive; without the guard the iterates invert them.
"""

from __future__ import annotations

from unittest import mock

import numpy as np
import pytest

from latentsim.mesh import beam_tets
from latentsim.neural_modes import linear_modes
from latentsim.scene import build_elastic
from latentsim.solve.constrained import ConstrainedNewton, first_inversion, volume_signs

FLOAT64 = True
ONE_THREAD = True


def _positive_tets(rng, n=30, count=120):
    X = rng.standard_normal((n, 3))
    T = np.array([rng.choice(n, 4, replace=False) for _ in range(count)])
    flip = volume_signs(X, T) < 0
    T[flip, 1], T[flip, 2] = T[flip, 2].copy(), T[flip, 1].copy()
    return X, T


def _sampled_first_inversion(X, dx, T, samples=20001):
    for t in np.linspace(0.0, 1.0, samples)[1:]:
        if (volume_signs(X + t * dx, T) <= 0).any():
            return t
    return np.inf


@pytest.mark.parametrize("scale", [0.02, 0.1, 0.3, 1.0])
def test_first_inversion_is_the_first_zero_volume_along_the_step(scale):
    rng = np.random.default_rng(int(scale * 100))
    X, T = _positive_tets(rng)
    dx = scale * rng.standard_normal(X.shape)
    t = first_inversion(X, dx, T)
    t_sampled = _sampled_first_inversion(X, dx, T)
    if np.isinf(t_sampled):
        assert np.isinf(t)
    else:  # the sampled t is the first grid point past the root
        assert t_sampled - 1e-4 <= t <= t_sampled
        assert (volume_signs(X + 0.999 * t * dx, T) > 0).all() and (volume_signs(X + t * dx, T) <= 1e-9 * np.abs(volume_signs(X, T)).max()).any()


def test_first_inversion_ignores_elements_inverted_at_the_start():
    X, T = _positive_tets(np.random.default_rng(3), count=10)
    dx = np.zeros_like(X)
    assert np.isinf(first_inversion(X, dx, T))
    # element 0 turned inside out at x; a step that restores it is no inversion
    T_bad = T.copy()
    T_bad[0, 1], T_bad[0, 2] = T[0, 2], T[0, 1]
    assert volume_signs(X, T_bad)[0] < 0
    assert np.isinf(first_inversion(X, np.zeros_like(X), T_bad))


@pytest.fixture(scope="module")
def beam():
    """A clamped stvk_nm beam (0.6 x 0.1 x 0.1 m, 120 tets, nu 0.45), its 5 lowest modes, and 3 modal
    samples in [-0.3, 0.3]^5: at X + l every element positive (det F >= 0.87)."""
    V, T = beam_tets(6, 2, 2, 0.6, 0.1, 0.1, tets_per_cell=5)
    V, T = np.asarray(V, dtype=np.float64), np.asarray(T, dtype=np.int64)
    arrays = {"rest_positions": V, "tets": T, "dirichlet": np.flatnonzero(V[:, 0] < 1e-12)}
    pot = build_elastic("tets", arrays, {"model": "stvk_nm", "youngs_modulus": 1e6, "poisson_ratio": 0.45, "density": 1000.0})
    lm = linear_modes(pot, 5, V)
    z = np.random.default_rng(0).uniform(-0.3, 0.3, (3, 5))
    return pot, V, T, lm, z


def _solve_all(pot, V, lm, z):
    solver = ConstrainedNewton(pot, V, lm.free_dofs)
    return [solver.solve(lm.modes @ zi, rtol=1e-5, max_iter=40) for zi in z]


def test_ground_truth_keeps_tets_positive_and_converges(beam):
    pot, V, T, lm, z = beam
    v0 = volume_signs(V, T)
    for zi, (x, info) in zip(z, _solve_all(pot, V, lm, z)):
        assert (volume_signs(V.reshape(-1) + lm.modes @ zi, T) > 0).all()
        assert info.converged and info.residual <= 1e-5 and info.iterations < 40 and info.blocked > 0  # the guard acted
        assert (volume_signs(x, T) / v0).min() > 0.5


def test_without_the_guard_the_iterates_turn_elements_inside_out(beam):
    """The case above is one the guard decides: unguarded (every step length allowed), each sample's
    exact-Hessian KKT steps turn elements inside out within the first iterations (by a twentieth of the
    largest rest volume at least; seen here: at the second or third iterate, by 0.09 to 5 of it).
    Where the unguarded iteration then ends (unconverged at the cap, or converged after many steps
    among inverted elements) depends on rounding, so it is not asserted."""
    pot, V, T, lm, z = beam
    scale = volume_signs(V, T).max()
    for zi in z:
        smallest = []

        def unguarded(self, x, dxf):
            smallest.append(volume_signs(x, self.tets).min() / scale)
            return 1.0

        with mock.patch.object(ConstrainedNewton, "inversion_free_step", unguarded):
            ConstrainedNewton(pot, V, lm.free_dofs).solve(lm.modes @ zi, rtol=1e-5, max_iter=6)
        assert smallest[0] > 0 and min(smallest) < -0.05, smallest

"""Tests of the one Newton minimiser and its line search (latentsim.solve.newton).

Small problems with known minimisers, each written against the problem protocol:
- a strictly convex quadratic: the full Newton step lands on the minimiser in one iteration;
- the Rosenbrock function: the full step overshoots far from the valley, the Armijo backtracking
  shortens it, every accepted step lowers the energy, and Newton converges to (1, 1);
- a quadratic under linear constraints (the KKT direction): iterates stay feasible and end at
  the constrained minimiser of the closed-form KKT system;
- the line search itself: halving until Armijo, None where no length down to ``min_step``
  works, the full step below the energy's resolution, the constrained solver's variant that
  searches anyway.
"""

from __future__ import annotations

import numpy as np
import pytest

from latentsim.solve.newton import LineSearch, line_search, minimise


class DenseNewton:
    """E, g, H of a smooth function; Newton direction by a dense solve, optionally on {C^T dx = 0}."""

    def __init__(self, energy, gradient, hessian, tol=1e-10, C=None):
        self.energy, self.gradient, self.hessian, self.tol, self.C = energy, gradient, hessian, tol, C
        self.energies, self.steps, self.failures = [], [], 0

    def projected(self, g):
        if self.C is None:
            return g
        return g - self.C @ np.linalg.solve(self.C.T @ self.C, self.C.T @ g)

    def stop(self, x, k):
        self.g = self.gradient(x)
        return np.linalg.norm(self.projected(self.g)) <= self.tol

    def direction(self, x, k):
        H, g = self.hessian(x), self.g
        if self.C is None:
            dx = -np.linalg.solve(H, g)
        else:  # [H C; C^T 0] [dx; mu] = [-g; 0]
            n, c = len(x), self.C.shape[1]
            K = np.block([[H, self.C], [self.C.T, np.zeros((c, c))]])
            dx = np.linalg.solve(K, np.concatenate([-g, np.zeros(c)]))[:n]
        slope = float(g @ dx)
        return (dx, slope) if slope < 0 else None

    def trial(self, x, alpha, searching):
        return self.energy(x), alpha

    def accept(self, trial, e_old, seconds):
        assert seconds >= 0.0
        self.energies.append((e_old, trial.energy))
        self.steps.append(trial.alpha)

    def line_search_failed(self, k, seconds):
        self.failures += 1
        raise RuntimeError(f"line search failed at {k}")


def quadratic(A, b):
    return (lambda x: 0.5 * x @ A @ x - b @ x), (lambda x: A @ x - b), (lambda x: A)


def rosenbrock():
    def e(x):
        return (1 - x[0]) ** 2 + 100 * (x[1] - x[0] ** 2) ** 2

    def g(x):
        return np.array([-2 * (1 - x[0]) - 400 * x[0] * (x[1] - x[0] ** 2), 200 * (x[1] - x[0] ** 2)])

    def h(x):
        return np.array([[2 - 400 * (x[1] - 3 * x[0] ** 2), -400 * x[0]], [-400 * x[0], 200.0]])

    return e, g, h


def test_a_quadratic_is_minimised_by_one_full_step():
    rng = np.random.default_rng(0)
    Q = rng.standard_normal((5, 5))
    A, b = Q @ Q.T + 5 * np.eye(5), rng.standard_normal(5)
    e, g, h = quadratic(A, b)
    problem = DenseNewton(e, g, h)
    x, info = minimise(problem, np.zeros(5), e(np.zeros(5)), LineSearch(), 10)
    assert info.stopped and info.iterations == 1 and problem.steps == [1.0]
    assert np.allclose(x, np.linalg.solve(A, b), rtol=1e-12, atol=1e-12)
    assert info.energy == pytest.approx(e(x), rel=1e-15)


def test_rosenbrock_needs_the_line_search_and_converges():
    e, g, h = rosenbrock()
    problem = DenseNewton(e, g, h, tol=1e-9)
    x0 = np.array([-1.2, 1.0])
    x, info = minimise(problem, x0, e(x0), LineSearch(), 100)
    assert info.stopped
    assert np.allclose(x, [1.0, 1.0], atol=1e-8)
    assert min(problem.steps) < 1.0  # some full steps overshoot: backtracked
    assert problem.steps[-1] == 1.0  # quadratic convergence near the minimum takes full steps
    for e_old, e_new in problem.energies:
        assert e_new < e_old  # every accepted step decreases E (Armijo with a negative slope)


def test_the_kkt_direction_keeps_the_iterates_feasible_and_ends_at_the_constrained_minimum():
    rng = np.random.default_rng(1)
    n, c = 6, 2
    # a convex non-quadratic energy: E = 1/2 x^T A x - b^T x + sum x_i^4 / 4
    Q = rng.standard_normal((n, n))
    A, b = Q @ Q.T + np.eye(n), rng.standard_normal(n)
    C = rng.standard_normal((n, c))
    x0 = rng.standard_normal(n)

    def energy(x):
        return 0.5 * x @ A @ x - b @ x + 0.25 * np.sum(x**4)

    def gradient(x):
        return A @ x - b + x**3

    def hessian(x):
        return A + np.diag(3 * x**2)

    problem = DenseNewton(energy, gradient, hessian, tol=1e-11, C=C)
    x, info = minimise(problem, x0, energy(x0), LineSearch(), 50)
    assert info.stopped and info.iterations >= 2
    assert np.allclose(C.T @ (x - x0), 0.0, atol=1e-12)  # C^T dx = 0 at every step
    # the constrained minimum: the gradient is a combination of the constraint columns
    mu = np.linalg.lstsq(C, gradient(x), rcond=None)[0]
    assert np.linalg.norm(gradient(x) - C @ mu) <= 1e-10
    # and lower than any other feasible point nearby
    for _ in range(5):
        d = rng.standard_normal(n)
        d -= C @ np.linalg.solve(C.T @ C, C.T @ d)
        assert energy(x + 1e-3 * d) > energy(x)


def test_max_iterations_and_no_descent_end_the_iteration():
    e, g, h = rosenbrock()
    x0 = np.array([-1.2, 1.0])
    x, info = minimise(DenseNewton(e, g, h), x0, e(x0), LineSearch(), 2)
    assert info.status == "max_iterations" and info.iterations == 2 and not info.stopped
    assert info.energy == e(x) < e(x0)
    # a maximum: the Newton step climbs, so the problem reports no descent direction
    neg = DenseNewton(lambda x: -x @ x, lambda x: -2 * x, lambda x: -2 * np.eye(2))
    x, info = minimise(neg, np.ones(2), -2.0, LineSearch(), 5)
    assert info.status == "no descent" and info.iterations == 0 and np.array_equal(x, np.ones(2))


def test_line_search_halves_until_armijo_and_reports_failure():
    calls = []

    def trial(x, alpha, searching):
        calls.append((alpha, searching))
        return float(x @ x), None

    # E = |x|^2 from x = 1 along dx = -4: the full step lands at -3 (E 9 > 1), a half at -1 (E 1,
    # not below 1 + c alpha slope), a quarter at 0 (E 0)
    t = line_search(trial, np.ones(1), 1.0, -4.0 * np.ones(1), -8.0, LineSearch())
    assert t.alpha == 0.25 and t.x[0] == 0.0 and t.energy == 0.0
    assert calls == [(1.0, True), (0.5, True), (0.25, True)]
    # an ascent "direction" with a claimed negative slope: nothing passes, down to min_step
    calls.clear()
    assert line_search(trial, np.ones(1), 1.0, np.ones(1), -2.0, LineSearch(min_step=1e-3)) is None
    assert [a for a, _ in calls] == [0.5**k for k in range(10)]  # 1 ... 2^-9 >= 1e-3 > 2^-10
    # a non-finite trial energy is rejected like a too-high one
    t = line_search(lambda x, a, s: (np.inf if a == 1.0 else 0.0, None), np.ones(1), 1.0, -np.ones(1), -2.0, LineSearch())
    assert t.alpha == 0.5


def test_below_the_energys_resolution_the_full_step_is_taken():
    calls = []

    def trial(x, alpha, searching):
        calls.append((alpha, searching))
        return 2.0, None  # higher: Armijo would reject every length

    # -slope = 1e-13 |E|: below the default resolution 1e-12 |E|
    t = line_search(trial, np.zeros(2), 1.0, np.ones(2), -1e-13, LineSearch())
    assert t.alpha == 1.0 and calls == [(1.0, False)] and np.array_equal(t.x, np.ones(2))
    # the constrained solver's variant searches first and takes the full step only after
    calls.clear()
    kkt = LineSearch(min_step=0.1, energy_resolution=1e-12, search_unresolvable=True)
    t = line_search(trial, np.zeros(2), 1.0, np.ones(2), -1e-13, kkt)
    assert t.alpha == 1.0 and calls == [(1.0, True), (0.5, True), (0.25, True), (0.125, True), (1.0, False)]
    # ... and fails on a resolvable decrease, for the problem to decide
    assert line_search(trial, np.zeros(2), 1.0, np.ones(2), -1.0, kkt) is None


def test_a_failed_line_search_is_the_problems_to_handle():
    """The problem's ``line_search_failed`` may raise (the time-stepping solvers) or return, after
    which x is evaluated again as the next iteration (the constrained solver's damping)."""
    e, g, h = rosenbrock()
    problem = DenseNewton(e, g, h)
    problem.stop = lambda x, k: False
    problem.direction = lambda x, k: (np.array([1.0, 0.0]), -1.0)  # uphill along x from the minimum (1, 1)
    with pytest.raises(RuntimeError, match="line search failed at 0"):
        minimise(problem, np.array([1.0, 1.0]), 0.0, LineSearch(), 5)

    class Retry(DenseNewton):
        def line_search_failed(self, k, seconds):
            self.failures += 1

    retry = Retry(e, g, h)
    retry.direction = lambda x, k: (np.array([1.0, 0.0]), -1.0)
    retry.stop = lambda x, k: False
    x, info = minimise(retry, np.array([1.0, 1.0]), 0.0, LineSearch(), 3)
    assert retry.failures == 3 and info.status == "max_iterations" and np.array_equal(x, [1.0, 1.0])

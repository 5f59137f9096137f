r"""Newton's method with a backtracking (Armijo) line search: the one minimiser of every solver.

Every solver of the package minimises an energy E over its own unknowns x,

- the positions of the free DoFs, one implicit-Euler step (Martin et al. 2011; Li et al. 2025,
  Eq. 1; :mod:`latentsim.solve.implicit_euler`),
- the reduced coordinates q of a subspace (Fulton et al. 2019; :mod:`latentsim.solve.reduced`),
- the positions under linear constraints, the Neural Modes ground truth (Wang et al. 2024, Eq. 9;
  :mod:`latentsim.solve.constrained`),

by the iteration (Nocedal and Wright 2006, Algorithm 3.1 for the line search)

    x_{k+1} = x_k + alpha_k dx_k,
    alpha_k = the first of 1, 1/2, 1/4, ... (>= min_step) with
              E(x_k + alpha dx_k) <= E(x_k) + c alpha g_k . dx_k      (Armijo, c = ``armijo``),

where the problem supplies the direction dx_k and the slope g_k . dx_k < 0: the sparse solve of
the full space, the dense r x r solve (or L-BFGS recursion) of a subspace, the KKT solve with
Levenberg shifts.  Near convergence the predicted decrease -g . dx falls below what E resolves in
float64 (``energy_resolution`` |E|); Armijo would then compare round-off, so the full step is
taken.

A problem is any object with

- ``stop(x, k) -> bool``: evaluates what its tests need at x (and keeps it for ``direction``);
  True ends the iteration (converged, or the problem's own stopping rule).  It may raise.
- ``direction(x, k) -> (dx, slope) | None``: the step at the x of the last ``stop`` and
  g . dx; None when there is no descent direction (the iteration ends).
- ``trial(x, alpha, searching) -> (E, payload)``: E at a trial point x = x_k + alpha dx_k,
  with whatever the problem computed alongside (given back in the accepted :class:`Trial`);
  ``searching`` is False for the full step taken without a search (unresolvable decrease).
- ``accept(trial, e_old, seconds)``: the line search accepted ``trial`` (``seconds``: its time).
- ``line_search_failed(k, seconds)``: no step length down to ``min_step`` met Armijo: raise,
  or return to evaluate x_k again as iteration k + 1.
- optionally ``max_step(x, dx) -> alpha0`` in (0, 1]: the largest step the search may start from
  (:func:`max_step` of the problem's terms: ``IMPACT_SAFETY`` times the first fraction of dx at which
  a term turns infinite, a barrier's time of impact, so that every iterate stays where all are finite).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

__all__ = ["IMPACT_SAFETY", "LineSearch", "NewtonInfo", "Trial", "first_impact", "line_search", "max_step", "minimise"]

#: the fraction of the first impact a line search starts from (as IPC's line search does)
IMPACT_SAFETY = 0.9


def first_impact(terms, x, dx, frame=None) -> float:
    """The first fraction t >= 0 of the straight step x -> x + dx (n, 3) at which one of ``terms`` turns
    infinite: the least of their ``first_impact(x, dx, frame)`` (``physics.base``; with ``frame``, along the
    step it describes); inf where none does, or none has one."""
    return min((float(t.first_impact(x, dx, frame)) for t in terms if hasattr(t, "first_impact")), default=math.inf)


def max_step(terms, x, dx, safety: float = IMPACT_SAFETY) -> float:
    """The largest step fraction alpha in (0, 1] a line search along x + t dx starts from: ``safety`` times
    the terms' :func:`first_impact`, 1 when none comes that close within the whole step."""
    return min(1.0, safety * first_impact(terms, x, dx))


@dataclass
class LineSearch:
    """Settings of the backtracking line search.

    armijo : the sufficient-decrease constant c.
    min_step : the smallest step length tried.
    energy_resolution : the relative decrease |g . dx| / |E| below which E cannot resolve the
        Armijo test.
    search_unresolvable : False: below the resolution take the full step without searching;
        True: search anyway and take the full step only when the search fails (where it
        would fail on a resolvable decrease, the problem's ``line_search_failed`` decides).
    """

    armijo: float = 1e-4
    min_step: float = 1e-10
    energy_resolution: float = 1e-12
    search_unresolvable: bool = False


@dataclass
class Trial:
    """An accepted step: its length, the new iterate and energy, and the problem's payload."""

    alpha: float
    x: np.ndarray
    energy: float
    payload: object = None


@dataclass
class NewtonInfo:
    """How :func:`minimise` ended: ``status`` 'stopped' (the problem's ``stop`` held),
    'no descent' (``direction`` gave None) or 'max_iterations'; ``iterations`` the k it ended at;
    ``energy`` E at the returned x."""

    iterations: int
    energy: float
    status: str

    @property
    def stopped(self) -> bool:
        return self.status == "stopped"


def line_search(trial, x, e: float, dx, slope: float, settings: LineSearch, alpha0: float = 1.0) -> Trial | None:
    """Backtracking from the full step x + dx (or the first ``alpha0`` of it: the most a problem
    with colliders allows, its ``max_step``) until Armijo holds (see the module docstring).

    Parameters
    ----------
    trial : the problem's ``trial(x, alpha, searching) -> (E, payload)``.
    x, dx : the iterate and the direction (any shape, the same).
    e, slope : E(x) and g . dx (< 0).

    Returns
    -------
    The accepted :class:`Trial`, or None when no step length down to ``min_step`` met Armijo
    on a decrease E can resolve.
    """
    s = settings
    resolvable = -slope > s.energy_resolution * max(abs(e), 1e-300)
    if resolvable or s.search_unresolvable:
        alpha = float(alpha0)
        while alpha >= s.min_step:
            x_try = x + alpha * dx
            e_try, payload = trial(x_try, alpha, True)
            if np.isfinite(e_try) and e_try <= e + s.armijo * alpha * slope:
                return Trial(alpha, x_try, e_try, payload)
            alpha *= 0.5
        if resolvable:
            return None
    x_try = x + alpha0 * dx
    e_try, payload = trial(x_try, float(alpha0), False)
    return Trial(float(alpha0), x_try, e_try, payload)


def minimise(problem, x, e: float, settings: LineSearch, max_iterations: int):
    """Newton's method with the line search on ``problem`` from x (E(x) = e).

    Iteration k = 0, 1, ..., max_iterations: ``stop`` at x_k; then (k < max_iterations) the
    direction, the line search and the step.

    Returns
    -------
    x : the last iterate, info : :class:`NewtonInfo`.
    """
    for k in range(max_iterations + 1):
        if problem.stop(x, k):
            return x, NewtonInfo(k, e, "stopped")
        if k == max_iterations:
            break
        step = problem.direction(x, k)
        if step is None:
            return x, NewtonInfo(k, e, "no descent")
        dx, slope = step
        t0 = time.perf_counter()
        alpha0 = problem.max_step(x, dx) if hasattr(problem, "max_step") else 1.0
        accepted = line_search(problem.trial, x, e, dx, slope, settings, alpha0)
        seconds = time.perf_counter() - t0
        if accepted is None:
            problem.line_search_failed(k, seconds)
            continue
        problem.accept(accepted, e, seconds)
        x, e = accepted.x, accepted.energy
    return x, NewtonInfo(max_iterations, e, "max_iterations")

r"""Constrained Newton: minimise a scene's elastic energy subject to linear constraints on the positions.

The solver of the Neural Modes ground truth (Wang et al. 2024, Eq. 9; ``latentsim.neural_modes``):

    n(z) = argmin_x E(x)   s.t.   C^T (x - X - l) = 0,

by Newton's method on the KKT system (the one Newton loop and line search of
``latentsim.solve.newton``), with the elastic Hessian of the compiled assembly
(``latentsim.solve.assembly``): the direction dx solves

    [H  C] [dx]   [-g]
    [C' 0] [mu] = [ 0]

by one multi-right-hand-side solve with one factorisation of H (Schur complement of the small
block).  Iterates stay feasible (C^T dx = 0), and a backtracking line search on E keeps the energy
decreasing.  For a free-floating object the rigid motions that keep l^T y = 0 leave E unchanged; a
tiny multiple of M is added to H (Levenberg) so that the solve is defined.  The exact Hessian is used
when it yields a descent direction whose full step inverts no tetrahedron.

Tetrahedra.  Neither StVK energy (``physics.tets``, ``physics.stvk_nm``) bars inversion: a reflected
element has E = (F^T F - I)/2 = 0, and only the volume term (finite at det F <= 0) opposes it.  Far
from the solution the exact Hessian is strongly indefinite, and its KKT step (a descent direction all
the same) can turn elements inside out; the iteration then settles among inverted elements, or at a
start near collapse moves along the boundary det F = 0, and does not converge.  So on a mesh with
tetrahedra the step is kept inversion-free: a direction whose full step would invert an element that
is positive now (the first root in (0, 1] of the cubic det D(x + t dx), :func:`first_inversion`) is
damped like a non-descent one (Levenberg shifts by multiples of M until the full step inverts none),
and the line search starts from at most ``INVERSION_SAFETY`` times that root (``max_step``).  Near the
solution the full Newton step inverts nothing and the iteration is the plain exact-Hessian Newton.  A
start with an inverted element is solved without the guard (no inversion-free path leads from it).
The guard cannot help where the energy itself drives elements to collapse (an inversion-free minimum
that does not exist, at modal amplitudes well beyond the armadillo's box): the steps then stop short
of det F = 0 and the solve ends unconverged (``CompliantInfo.blocked``: the iterations the guard
shortened).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from latentsim.physics.incremental_potential import IncrementalPotential
from latentsim.physics.stvk_nm import TetsNM
from latentsim.physics.tets import StVKTets
from latentsim.solve.assembly import CompiledAssembly
from latentsim.solve.modes import stiffness_matrix
from latentsim.solve.newton import LineSearch, minimise
from latentsim.solve.sparse import HessianPattern, LinearSolver, NotPositiveDefinite

# the KKT iteration's line search: below 1e-13 |E| the search still runs, and the full step is
# taken only where it fails
KKT_LINE_SEARCH = LineSearch(armijo=1e-4, min_step=1e-10, energy_resolution=1e-13, search_unresolvable=True)
# the line search starts at most this fraction of the way to the first inversion of a tetrahedron
INVERSION_SAFETY = 0.9
# the energy terms whose stencils are tetrahedra (positively oriented at rest)
TET_TERMS = (StVKTets, TetsNM)


def _triple(a, b, c) -> np.ndarray:
    """Row-wise triple products a . (b x c) of (E, 3) arrays."""
    return np.einsum("ij,ij->i", a, np.cross(b, c))


def volume_signs(x, tets) -> np.ndarray:
    """det [x1 - x0, x2 - x0, x3 - x0] of each tetrahedron (E,): six times its signed volume at x (3n,)."""
    x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    a1, a2, a3 = (x[tets[:, 1:]] - x[tets[:, :1]]).transpose(1, 0, 2)
    return _triple(a1, a2, a3)


def first_inversion(x, dx, tets) -> float:
    """The least t in (0, 1] at which a tetrahedron with positive volume at x has zero volume at x + t dx.

    det D(x + t dx) = c0 + c1 t + c2 t^2 + c3 t^3, D = [x1 - x0, x2 - x0, x3 - x0] = [a1, a2, a3] and
    likewise [b1, b2, b3] of dx, with c0 = [a1 a2 a3], c1 = [b1 a2 a3] + [a1 b2 a3] + [a1 a2 b3],
    c2 = [a1 b2 b3] + [b1 a2 b3] + [b1 b2 a3], c3 = [b1 b2 b3] ([.] the triple product).  The cubic is
    monotone between 0, its critical points in (0, 1) and 1: the first of these where it is <= 0 brackets
    the first root, found by bisection.  Elements already inverted or flat at x are not watched.

    Parameters
    ----------
    x, dx : (3n,) or (n, 3) float, positions and step.
    tets : (E, 4) int.

    Returns
    -------
    t in (0, 1], or inf when the whole step inverts no element.
    """
    x, dx = np.asarray(x, dtype=np.float64).reshape(-1, 3), np.asarray(dx, dtype=np.float64).reshape(-1, 3)
    A = x[tets[:, 1:]] - x[tets[:, :1]]
    B = dx[tets[:, 1:]] - dx[tets[:, :1]]
    (a1, a2, a3), (b1, b2, b3) = A.transpose(1, 0, 2), B.transpose(1, 0, 2)
    c0 = _triple(a1, a2, a3)
    c1 = _triple(b1, a2, a3) + _triple(a1, b2, a3) + _triple(a1, a2, b3)
    c2 = _triple(a1, b2, b3) + _triple(b1, a2, b3) + _triple(b1, b2, a3)
    c3 = _triple(b1, b2, b3)
    # critical points: c1 + 2 c2 t + 3 c3 t^2 = 0 (a quadratic, or linear where c3 = 0)
    disc = c2 * c2 - 3.0 * c3 * c1
    sq = np.sqrt(np.maximum(disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        quad = c3 != 0
        r1 = np.where(quad, (-c2 - sq) / (3.0 * c3), np.where(c2 != 0, -c1 / (2.0 * c2), np.inf))
        r2 = np.where(quad, (-c2 + sq) / (3.0 * c3), np.inf)
    r1, r2 = np.where(disc >= 0, r1, np.inf), np.where(disc >= 0, r2, np.inf)
    T = np.stack([np.zeros_like(c0), r1, r2, np.ones_like(c0)], axis=1)
    T = np.sort(np.where((T >= 0) & (T <= 1), T, 1.0), axis=1)
    P = ((c3[:, None] * T + c2[:, None]) * T + c1[:, None]) * T + c0[:, None]
    crossed = (c0 > 0)[:, None] & (P <= 0)
    hit = np.flatnonzero(crossed.any(axis=1))
    if not hit.size:
        return np.inf
    k = np.argmax(crossed[hit], axis=1)
    lo, hi = T[hit, k - 1], T[hit, k]
    c = [ci[hit] for ci in (c0, c1, c2, c3)]
    for _ in range(60):  # bisection of each bracket to round-off
        mid = 0.5 * (lo + hi)
        positive = ((c[3] * mid + c[2]) * mid + c[1]) * mid + c[0] > 0
        lo, hi = np.where(positive, mid, lo), np.where(positive, hi, mid)
    return float(lo.min())


@dataclass
class CompliantInfo:
    iterations: int
    residual: float  # ||g + mu c|| / ||g_0|| on free DoFs (KKT stationarity)
    constraint: float  # |l^T y| / (|l| |y|)
    energy: float
    levenberg: int  # damping increases (a direction that is no descent, or whose full step inverts a tetrahedron)
    converged: bool  # residual <= rtol (not the stall rule or the iteration cap)
    blocked: int  # iterations whose step the inversion guard shortened (more damping, or cut short by max_step)


class ConstrainedNewton:
    """Minimise the elastic energy subject to C^T (x - X - l) = 0, for one scene and many l.

    C = [l] (``metric='euclidean'``, the paper's l^T y; or M l with
    ``metric='mass'``, l^T M y, the inner product in which generalised modes are
    orthogonal: then a single mode's n(z) -> X + l exactly as z -> 0, while
    with l^T y and a non-uniform lumped mass a correction of relative size
    ~|M - mean(M)| remains) with Dirichlet constraints (prescribed DoFs removed), and
    C = [l, M R] for a free-floating object (R the rigid modes): with the
    single constraint l^T y = 0 a free body escapes into rigid motions (a
    translation or rotation satisfies l^T (x - X) = |l|^2 at zero energy), so
    y is also held M-orthogonal to the rigid modes, the linearised rigid-frame
    condition that also defines the modes themselves.
    """

    def __init__(self, potential: IncrementalPotential, rest_positions, free_dofs=None, rigid=None, metric="euclidean", reg=1e-8):
        if metric not in ("euclidean", "mass"):
            raise ValueError(f"metric '{metric}': use 'euclidean' (l^T y, the paper) or 'mass' (l^T M y)")
        self.metric = metric
        self.pot = potential
        self.X = np.asarray(rest_positions, dtype=np.float64)
        n = len(self.X)
        self.n = n
        self.free = np.arange(3 * n) if free_dofs is None else np.asarray(free_dofs, dtype=np.int64)
        self.stencils = [t.stencils.cpu().numpy() for t in potential.terms]
        tets = [st for t, st in zip(potential.terms, self.stencils) if isinstance(t, TET_TERMS)]
        self.tets = np.concatenate(tets) if tets else None  # watched for inversion along each step
        self.pattern = HessianPattern(n, self.stencils, self.free)
        m3 = np.repeat(potential.masses.cpu().numpy().astype(np.float64), 3)
        self.m3 = m3
        self.fixed_constraints = None
        if rigid is not None:
            self.fixed_constraints = (m3[:, None] * np.asarray(rigid, dtype=np.float64))[self.free]
        K0, _ = stiffness_matrix(potential, self.X, self.free)
        self.diag = reg * abs(K0.diagonal()).max() / m3.max() * m3
        # Levenberg shifts are multiples of M, starting at the lowest nonzero rest eigenvalue's scale
        self.mass_diagonal = m3[self.free]
        # the scene's fastest SPD solver (PARDISO on tets, with its symbolic analysis reused); an
        # indefinite exact Hessian (at large deformations the rule, not the exception) is solved by
        # the same solver's symmetric indefinite factorisation (``LinearSolver.solve_indefinite``)
        self.linear = LinearSolver(self.pattern)
        self.damping0 = 1e-3 * abs(K0.diagonal()).mean() / m3.mean()
        # the simulator's compiled kernels
        self.assembly = CompiledAssembly.of(potential.terms, self.pattern, n, threads=min(2, torch.get_num_threads()))

    def energy(self, x) -> float:
        """Elastic energy at x (3n,)."""
        return float(self.assembly.energy(x.reshape(-1, 3)))

    def grad_hess(self, x, project):
        """Elastic gradient (3n,) and the free-DoF Hessian (+ the regularising diagonal), upper CSR."""
        return self.assembly.gradient_hessian(x.reshape(-1, 3), self.diag, project)

    def constraints(self, l) -> np.ndarray:
        """C (f, c): the columns whose inner products with y must vanish."""
        c = np.asarray(l, dtype=np.float64) * (self.m3 if self.metric == "mass" else 1.0)
        cols = [] if not np.any(l) else [c[self.free, None]]
        if self.fixed_constraints is not None:
            cols.append(self.fixed_constraints)
        return np.concatenate(cols, axis=1) if cols else np.zeros((len(self.free), 0))

    def solve(self, l, y0=None, rtol: float = 1e-5, etol: float = 1e-7, max_iter: int = 60):
        """x (3n,) minimising E s.t. C^T (x - X - l) = 0, from X + l + y0 (y0 made feasible).

        Stops when the KKT residual ||g - C (C^T C)^-1 C^T g|| is at most
        ``rtol`` times the force norm at X + l, or when three successive steps
        each lower E by less than ``etol`` |E| (the buckled sheet's shallow
        valleys), or after ``max_iter`` iterations.
        """
        X = self.X.reshape(-1)
        l = np.asarray(l, dtype=np.float64)
        C = self.constraints(l)
        CtC = C.T @ C
        y = np.zeros_like(X)
        if y0 is not None:
            yf = np.asarray(y0, dtype=np.float64)[self.free]
            if C.shape[1]:
                yf = yf - C @ np.linalg.solve(CtC, C.T @ yf)
            y[self.free] = yf
        g_ref = max(float(np.linalg.norm(self.assembly.energy_gradient((X + l).reshape(-1, 3))[1][self.free])), 1e-300)
        x0 = X + l + y
        guard = self.tets is not None and bool((volume_signs(x0, self.tets) > 0).all())
        problem = _KKTProblem(self, C, rtol * g_ref, etol, guard)
        x, result = minimise(problem, x0, self.energy(x0), KKT_LINE_SEARCH, max_iter)
        yv = (x - X - l)[self.free]
        cons = abs(C[:, 0] @ yv) / max(np.linalg.norm(C[:, 0]) * np.linalg.norm(yv), 1e-300) if np.any(l) else 0.0
        converged = problem.residual <= problem.tolerance
        return x, CompliantInfo(result.iterations, problem.residual / g_ref, cons, result.energy, problem.levenberg, converged, problem.blocked)

    def inversion_free_step(self, x, dxf) -> float:
        """The largest step length in (0, 1] for the line search along the free-DoF step dxf: 1 when
        the full step inverts no tetrahedron, else ``INVERSION_SAFETY`` times the first inversion."""
        if self.tets is None:
            return 1.0
        step = np.zeros_like(x)
        step[self.free] = dxf
        t = first_inversion(x, step, self.tets)
        return 1.0 if t > 1.0 else INVERSION_SAFETY * t

    def _direction(self, U, gf, C):
        """dx minimising the quadratic model on {C^T dx = 0}: a - B (C^T B)^{-1} C^T a, with
        [a, B] = H^-1 [-g, C] in one multi-right-hand-side solve; U is H's upper triangle."""
        rhs = np.column_stack([-gf, C])
        try:
            sol = self.linear.solve(U, rhs)
        except NotPositiveDefinite:  # the exact Hessian may be indefinite: the KKT step still exists
            sol = self.linear.solve_indefinite(U, rhs)
        sol = sol.reshape(len(gf), -1)
        a, B = sol[:, 0], sol[:, 1:]
        if not C.shape[1]:
            return a
        return a - B @ np.linalg.solve(C.T @ B, C.T @ a)


class _KKTProblem:
    """One constrained solve as the problem of :func:`latentsim.solve.newton.minimise`: the KKT
    residual test, the KKT direction with Levenberg shifts of the exact Hessian, and the stall
    rule (three successive steps each lowering E by less than ``etol`` |E|)."""

    def __init__(self, solver: ConstrainedNewton, C, tolerance: float, etol: float, guard: bool = False):
        self.solver, self.C, self.CtC, self.tolerance, self.etol = solver, C, C.T @ C, tolerance, etol
        self.guard = guard  # keep every step inversion-free (a mesh with tetrahedra, none inverted at the start)
        self.damping, self.stalls, self.levenberg, self.blocked = 0.0, 0, 0, 0
        self.residual = float("nan")
        self.alpha0 = 1.0  # the line search's first step length along the last direction

    def stop(self, x, it) -> bool:
        g, self.H = self.solver.grad_hess(x, project=False)
        gf = self.gf = g[self.solver.free]
        if not np.isfinite(gf).all():  # a finite energy whose gradient is not (a shell folded flat on itself)
            raise FloatingPointError(f"constrained Newton: a non-finite gradient at iteration {it} (the energy there {self.solver.energy(x):.6g})")
        C = self.C
        self.residual = r = float(np.linalg.norm(gf - C @ np.linalg.solve(self.CtC, C.T @ gf))) if C.shape[1] else float(np.linalg.norm(gf))
        return r <= self.tolerance or self.stalls >= 3

    def direction(self, x, it):
        # exact Hessian, shifted by a multiple of M (Levenberg) until the step is a descent
        # direction (for the KKT step, dx^T (H + d M) dx = -g^T dx: positive curvature) whose full
        # step inverts no tetrahedron (a larger shift: a shorter step, nearer the M-gradient's)
        sv, H, gf = self.solver, self.H, self.gf
        blocked = False
        while True:
            Hs = H
            if self.damping:
                Hs = H.copy()
                Hs.data[sv.pattern.diagonal_slots] += self.damping * sv.mass_diagonal
            dx = sv._direction(Hs, gf, self.C)
            self.alpha0 = sv.inversion_free_step(x, dx) if self.guard and gf @ dx < 0 else 1.0
            blocked = blocked or self.alpha0 < 1.0
            if (gf @ dx < 0 and self.alpha0 == 1.0) or self.damping > 1e12 * sv.damping0:
                break
            self.damping = max(4 * self.damping, sv.damping0)
            self.levenberg += 1
        if not gf @ dx < 0:
            return None  # the projected gradient is at round-off level
        self.blocked += blocked
        self.damping = 0.25 * self.damping if self.damping > sv.damping0 else 0.0
        slope = float(gf @ dx)
        step = np.zeros_like(x)
        step[sv.free] = dx
        return step, slope

    def max_step(self, x, dx):
        # at the damping cap a direction may still invert an element before its full step
        return self.alpha0

    def trial(self, x, alpha, searching):
        return self.solver.energy(x), None

    def accept(self, trial, e_old, seconds):
        self.stalls = self.stalls + 1 if e_old - trial.energy < self.etol * abs(e_old) else 0

    def line_search_failed(self, it, seconds):
        # a resolvable decrease that no step length reaches: damp more and retry from x
        self.damping = max(4 * self.damping, self.solver.damping0)
        self.stalls += 1


def compliant_mode(potential, rest_positions, l, y0=None, free_dofs=None, rigid=None, metric="euclidean", **kwargs):
    """One ground-truth sample of Eq. 9; returns (x (3n,), CompliantInfo)."""
    return ConstrainedNewton(potential, rest_positions, free_dofs, rigid, metric).solve(l, y0, **kwargs)

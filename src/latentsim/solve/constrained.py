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
when it yields a descent direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from latentsim.physics.incremental_potential import IncrementalPotential
from latentsim.solve.assembly import CompiledAssembly
from latentsim.solve.modes import stiffness_matrix
from latentsim.solve.newton import LineSearch, minimise
from latentsim.solve.sparse import HessianPattern, LinearSolver, NotPositiveDefinite

# the KKT iteration's line search: below 1e-13 |E| the search still runs, and the full step is
# taken only where it fails
KKT_LINE_SEARCH = LineSearch(armijo=1e-4, min_step=1e-10, energy_resolution=1e-13, search_unresolvable=True)


@dataclass
class CompliantInfo:
    iterations: int
    residual: float  # ||g + mu c|| / ||g_0|| on free DoFs (KKT stationarity)
    constraint: float  # |l^T y| / (|l| |y|)
    energy: float
    levenberg: int  # damping increases (indefinite exact Hessian on the constraint space)


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
        problem = _KKTProblem(self, C, rtol * g_ref, etol)
        x0 = X + l + y
        x, result = minimise(problem, x0, self.energy(x0), KKT_LINE_SEARCH, max_iter)
        yv = (x - X - l)[self.free]
        cons = abs(C[:, 0] @ yv) / max(np.linalg.norm(C[:, 0]) * np.linalg.norm(yv), 1e-300) if np.any(l) else 0.0
        return x, CompliantInfo(result.iterations, problem.residual / g_ref, cons, result.energy, problem.levenberg)

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

    def __init__(self, solver: ConstrainedNewton, C, tolerance: float, etol: float):
        self.solver, self.C, self.CtC, self.tolerance, self.etol = solver, C, C.T @ C, tolerance, etol
        self.damping, self.stalls, self.levenberg = 0.0, 0, 0
        self.residual = float("nan")

    def stop(self, x, it) -> bool:
        g, self.H = self.solver.grad_hess(x, project=False)
        gf = self.gf = g[self.solver.free]
        C = self.C
        self.residual = r = float(np.linalg.norm(gf - C @ np.linalg.solve(self.CtC, C.T @ gf))) if C.shape[1] else float(np.linalg.norm(gf))
        return r <= self.tolerance or self.stalls >= 3

    def direction(self, x, it):
        # exact Hessian, shifted by a multiple of M (Levenberg) until the step is a descent
        # direction (for the KKT step, dx^T (H + d M) dx = -g^T dx: positive curvature)
        sv, H, gf = self.solver, self.H, self.gf
        while True:
            Hs = H
            if self.damping:
                Hs = H.copy()
                Hs.data[sv.pattern.diagonal_slots] += self.damping * sv.mass_diagonal
            dx = sv._direction(Hs, gf, self.C)
            if gf @ dx < 0 or self.damping > 1e12 * sv.damping0:
                break
            self.damping = max(4 * self.damping, sv.damping0)
            self.levenberg += 1
        if not gf @ dx < 0:
            return None  # the projected gradient is at round-off level
        self.damping = 0.25 * self.damping if self.damping > sv.damping0 else 0.0
        slope = float(gf @ dx)
        step = np.zeros_like(x)
        step[sv.free] = dx
        return step, slope

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

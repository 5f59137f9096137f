r"""Constrained Newton: minimise a scene's elastic energy subject to linear constraints on the positions.

The solver of the Neural Modes ground truth (Wang et al. 2024, Eq. 9; ``latentsim.neural_modes``):

    n(z) = argmin_x E(x)   s.t.   C^T (x - X - l) = 0,

by Newton's method on the KKT system, with the terms' per-stencil Hessians assembled sparsely
(``latentsim.solve.sparse``): the direction dx solves

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
import scipy.sparse
import scipy.sparse.linalg
import torch

from latentsim.physics.incremental_potential import IncrementalPotential
from latentsim.solve.implicit_euler import CompiledAssembly, stiffness_matrix
from latentsim.solve.sparse import HessianPattern, LinearSolver, NotPositiveDefinite, scatter_gradient, symmetric_from_upper


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
        # indefinite exact Hessian falls back to SuperLU on the full matrix (see _direction)
        self.linear = LinearSolver(self.pattern)
        self.damping0 = 1e-3 * abs(K0.diagonal()).mean() / m3.mean()
        # the simulator's compiled kernels (None without numba: the terms' closed forms below)
        self.assembly = CompiledAssembly.of(potential.terms, self.pattern, n, threads=min(2, torch.get_num_threads()))

    def energy(self, x) -> float:
        if self.assembly is not None:
            return float(self.assembly.energy(x.reshape(-1, 3)))
        with torch.no_grad():
            return float(self.pot.elastic(torch.from_numpy(x.reshape(-1, 3))))

    def grad_hess(self, x, project):
        """Elastic gradient (3n,) and the free-DoF Hessian (+ the regularising diagonal), upper CSR."""
        if self.assembly is not None:
            return self.assembly.gradient_hessian(x.reshape(-1, 3), self.diag, project)
        xt = torch.from_numpy(x.reshape(-1, 3))
        grads, blocks = [], []
        for term in self.pot.terms:
            g, H = term.local_gradient_hessian(term.gather(xt), project=project)
            grads.append(g.numpy())
            blocks.append(H.numpy())
        g = scatter_gradient(self.n, self.stencils, grads)
        return g, self.pattern.assemble(blocks, self.diag)  # upper triangle, the pattern's CSR

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
        g_ref = max(float(np.linalg.norm(self._gradient(X + l)[self.free])), 1e-300)
        x = X + l + y
        e = self.energy(x)
        damping, stalls, levenberg = 0.0, 0, 0
        for it in range(max_iter + 1):
            g, H = self.grad_hess(x, project=False)
            gf = g[self.free]
            r = float(np.linalg.norm(gf - C @ np.linalg.solve(CtC, C.T @ gf))) if C.shape[1] else float(np.linalg.norm(gf))
            if r <= rtol * g_ref or stalls >= 3 or it == max_iter:
                break
            # exact Hessian, shifted by a multiple of M (Levenberg) until the step is a descent
            # direction (for the KKT step, dx^T (H + d M) dx = -g^T dx: positive curvature)
            while True:
                Hs = H
                if damping:
                    Hs = H.copy()
                    Hs.data[self.pattern.diagonal_slots] += damping * self.mass_diagonal
                dx = self._direction(Hs, gf, C)
                if gf @ dx < 0 or damping > 1e12 * self.damping0:
                    break
                damping = max(4 * damping, self.damping0)
                levenberg += 1
            if not gf @ dx < 0:
                break  # the projected gradient is at round-off level
            damping = 0.25 * damping if damping > self.damping0 else 0.0
            slope = float(gf @ dx)
            step = np.zeros_like(x)
            step[self.free] = dx
            alpha = 1.0
            while alpha > 1e-10:
                e_try = self.energy(x + alpha * step)
                if np.isfinite(e_try) and e_try <= e + 1e-4 * alpha * slope:
                    break
                alpha *= 0.5
            else:
                if -slope > 1e-13 * max(abs(e), 1e-300):
                    damping = max(4 * damping, self.damping0)
                    stalls += 1
                    continue
                alpha, e_try = 1.0, self.energy(x + step)
            stalls = stalls + 1 if e - e_try < etol * abs(e) else 0
            x, e = x + alpha * step, e_try
        yv = (x - X - l)[self.free]
        cons = abs(C[:, 0] @ yv) / max(np.linalg.norm(C[:, 0]) * np.linalg.norm(yv), 1e-300) if np.any(l) else 0.0
        return x, CompliantInfo(it, r / g_ref, cons, e, levenberg)

    def _gradient(self, x):
        xt = torch.from_numpy(x.reshape(-1, 3))
        with torch.no_grad():
            grads = [t.local_gradient_hessian(t.gather(xt), project=False)[0].numpy() for t in self.pot.terms]
        return scatter_gradient(self.n, self.stencils, grads)

    def _direction(self, U, gf, C):
        """dx minimising the quadratic model on {C^T dx = 0}: a - B (C^T B)^{-1} C^T a, with
        [a, B] = H^-1 [-g, C] in one multi-right-hand-side solve; U is H's upper triangle."""
        rhs = np.column_stack([-gf, C])
        try:
            sol = self.linear.solve(U, rhs)
        except NotPositiveDefinite:  # the exact Hessian may be indefinite: the KKT step still exists
            sol = scipy.sparse.linalg.splu(symmetric_from_upper(U).tocsc()).solve(rhs)
        sol = sol.reshape(len(gf), -1)
        a, B = sol[:, 0], sol[:, 1:]
        if not C.shape[1]:
            return a
        return a - B @ np.linalg.solve(C.T @ B, C.T @ a)


def compliant_mode(potential, rest_positions, l, y0=None, free_dofs=None, rigid=None, metric="euclidean", **kwargs):
    """One ground-truth sample of Eq. 9; returns (x (3n,), CompliantInfo)."""
    return ConstrainedNewton(potential, rest_positions, free_dofs, rigid, metric).solve(l, y0, **kwargs)

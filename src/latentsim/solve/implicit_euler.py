"""Full-space implicit Euler: Newton's method on the incremental potential.

Each time step solves (Martin et al. 2011; Li et al. 2025, Eq. 1)

    x_t = argmin_x  E_total(x; x_{t-1}, x_{t-2})   s.t.  x_D = x*_D(t)

with Newton's method: per-stencil Hessians projected to positive semi-definite
(Teran et al. 2005) and assembled over the free DoFs only (Dirichlet DoFs are
removed from the system and set to their prescribed values), a sparse SPD
solve, and a backtracking (Armijo) line search on E_total.  A step has
converged when the 2-norm of the free-DoF gradient is at most
``tolerance * f_ref``, with ``f_ref`` the weight of the free vertices
(||m|| max(|g|, 1 m/s^2)), so the tolerance is a relative force residual.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse
import torch

from latentsim.physics.incremental_potential import IncrementalPotential
from latentsim.physics.kernels import add_at, inertia_gravity, split_stencils, term_kernel
from latentsim.solve.sparse import (
    BandedUpper,
    HessianPattern,
    LinearSolver,
    NotPositiveDefinite,
    scatter_gradient,
)


class NewtonFailed(RuntimeError):
    """A time step did not converge; carries the residual and iteration count."""

    def __init__(self, message, residual=float("nan"), iterations=0):
        super().__init__(message)
        self.residual = residual
        self.iterations = iterations


@dataclass
class NewtonSettings:
    """Settings of the per-step Newton solve (config key ``newton``)."""

    tolerance: float = 1e-6
    max_iterations: int = 100
    # return the last iterate instead of raising when max_iterations run out (the cheap
    # "one Newton iteration per frame" baseline of the cross-method comparison)
    accept_unconverged: bool = False
    linear_solver: str = "auto"
    armijo: float = 1e-4
    energy_resolution: float = 1e-12
    hessian: str = "exact_first"
    # with the compiled kernels, the line search's full-step trial is one pass for energy, gradient
    # and Hessian while the step is not expected to converge (iteration k + 1 < the previous
    # frame's iteration count); an accepted step then needs no second pass over the stencils (a
    # rejected trial, or one that converges earlier than the previous frame did, leaves its
    # Hessian unused)
    fused_trial: bool = True

    def __post_init__(self):
        if self.hessian not in ("projected", "exact_first"):
            raise ValueError(f"newton.hessian '{self.hessian}': use 'projected' or 'exact_first'")
    min_step: float = 1e-10


@dataclass
class StepInfo:
    """What one time step cost and how it ended."""

    iterations: int = 0
    gradient_norm: float = float("nan")
    projected: int = 0  # iterations that fell back to the projected Hessian (exact_first)
    hessians: int = 0  # Hessian passes, including fused trials whose Hessian went unused
    # "guess": the frame's initial-guess evaluations (once per frame); the others add up over its iterations
    timings: dict = field(default_factory=lambda: {"guess": 0.0, "energy": 0.0, "local": 0.0, "assembly": 0.0, "solve": 0.0})


_NO_GRADIENT = np.zeros(0)  # inertia_gravity without a gradient


def _dot(a, b) -> float:
    """a . b without BLAS: OpenBLAS threads its dot products from 10k entries, and waking its
    threads on a busy 2-core machine costs up to a scheduler tick (4 ms) per call."""
    return float(np.einsum("i,i->", a, b))


def rigidly_carried(x, D, targets):
    """x (n,3) moved by the rigid motion best mapping x[D] onto targets (Kabsch; translation if m < 3)."""
    src = x[D]
    cs, ct = src.mean(axis=0), np.asarray(targets).mean(axis=0)
    if len(D) < 3:
        return x + (ct - cs)
    U, _, Vt = np.linalg.svd((src - cs).T @ (targets - ct))
    d = np.sign(np.linalg.det(U @ Vt))
    R = (U @ np.diag([1.0, 1.0, d]) @ Vt).T
    return np.einsum("ij,kj->ik", x - cs, R) + ct


class CompiledAssembly:
    """The compiled kernels of a potential's elastic terms (``energy.kernels``), scattering each
    stencil's gradient and Hessian straight into the gradient and into the data of a
    ``HessianPattern``'s upper-triangular CSR (or, for ``banded=True``, the banded storage of
    ``sparse.BandedUpper``): no per-stencil blocks, no COO->CSR conversion.

    Parameters
    ----------
    kernels : one ``TermKernel`` per term (``term_kernel``); their stencils are split for
        ``threads`` (``energy.kernels.split_stencils``).
    pattern : the free-DoF Hessian pattern of those stencils.
    """

    def __init__(self, kernels, pattern: HessianPattern, n_vertices: int, banded: bool = False, threads: int = 1):
        self.kernels, self.pattern, self.n, self.banded = kernels, pattern, int(n_vertices), bool(banded)
        split_stencils(kernels, self.n, threads)
        self.slots = [pattern.stencil_slots(k.stencils) for k in kernels]
        self._diag_slots = pattern.diagonal_slots
        self._target_size = pattern.nnz
        if banded:
            pos = pattern.band_positions()
            self.slots = [np.where(s >= 0, pos[s], -1).astype(np.int32) for s in self.slots]
            self._diag_slots = pos[self._diag_slots]
            self._target_size = (pattern.bandwidth + 1) * pattern.shape[0]

    @classmethod
    def of(cls, terms, pattern: HessianPattern, n_vertices: int, banded: bool = False, threads: int = 1):
        """For the terms' kernels, or None when numba is missing or a term has none."""
        ks = [term_kernel(t) for t in terms]
        return cls(ks, pattern, n_vertices, banded, threads) if ks and all(k is not None for k in ks) else None

    def energy(self, x) -> float:
        """Elastic energy at x (n,3)."""
        return sum(k.energy(x) for k in self.kernels)

    def energy_gradient(self, x):
        """Elastic energy and its full gradient (3n,) in one pass."""
        grad = np.zeros(3 * self.n)
        return sum(k.energy_gradient(x, grad) for k in self.kernels), grad

    def gradient_hessian(self, x, diagonal, project: bool):
        """Elastic gradient (3n,) and the free-DoF Hessian plus ``diagonal`` (3n,) on its diagonal,
        as upper-triangular CSR or ``BandedUpper``; per-stencil PSD-projected or exact."""
        _, grad, U = self.energy_gradient_hessian(x, diagonal, project)
        return grad, U

    def energy_gradient_hessian(self, x, diagonal, project: bool):
        """``gradient_hessian`` with the elastic energy of the same pass in front: (E, grad, U)."""
        grad = np.zeros(3 * self.n)
        data = np.zeros(self._target_size)
        e = 0.0
        for k, slots in zip(self.kernels, self.slots):
            e += k.accumulate(x, grad, data, slots, project)
        add_at(data, self._diag_slots, np.ascontiguousarray(diagonal, dtype=np.float64)[self.pattern.free_dofs])
        p = self.pattern
        if self.banded:
            return e, grad, BandedUpper(data, p)
        return e, grad, scipy.sparse.csr_matrix((data, p.indices, p.indptr), shape=p.shape)


class ImplicitEuler:
    """Newton solver for one scene's incremental potential.

    Parameters
    ----------
    potential : IncrementalPotential (terms, masses, dt, g, dirichlet)
    settings : NewtonSettings
    kernels : None (default) runs the compiled per-stencil kernels of
        ``energy.kernels`` when numba imports and every term has one, else the
        terms' own closed forms and PyTorch energies (the reference); False
        forces the reference, True requires the kernels.
    threads : 1 or 2 threads for the kernels (two vertex-disjoint halves of each
        term's stencils run concurrently, ``energy.kernels.split_stencils``; the
        result is the same either way); default ``min(2, torch.get_num_threads())``,
        the budget a pipeline stage sets from its rule's ``threads``.
    """

    def __init__(self, potential: IncrementalPotential, settings: NewtonSettings | None = None, kernels=None, threads: int | None = None):
        self.potential = potential
        self.settings = settings or NewtonSettings()
        n = potential.n_vertices
        self.n = n
        self.masses = potential.masses.detach().cpu().numpy().astype(np.float64)
        self.g = potential.g.detach().cpu().numpy().astype(np.float64)
        self.dirichlet = potential.dirichlet.detach().cpu().numpy().astype(np.int64)
        free_v = np.ones(n, dtype=bool)
        free_v[self.dirichlet] = False
        self.free_mask = np.repeat(free_v, 3)
        self.free_dofs = np.flatnonzero(self.free_mask)
        self.stencils = [t.stencils.cpu().numpy() for t in potential.terms]
        self.pattern = HessianPattern(n, self.stencils, self.free_dofs)
        self.linear = LinearSolver(self.pattern, self.settings.linear_solver)
        m_free = self.masses[free_v]
        self.f_ref = float(np.linalg.norm(m_free) * max(np.linalg.norm(self.g), 1.0))
        self.m3 = np.repeat(self.masses, 3)
        self._mass_diagonal = self.m3 / potential.dt**2  # the inertia's Hessian, M / h^2
        # compiled per-stencil kernels (energy.kernels) when every term has one, unless kernels=False
        self.assembly = None
        if kernels is not False:
            self.assembly = CompiledAssembly.of(
                potential.terms, self.pattern, n, self.linear.method == "banded", min(2, int(threads or torch.get_num_threads()))
            )
        self.kernels = None if self.assembly is None else self.assembly.kernels
        self._last_iterations = 0  # the previous step's Newton iterations (NewtonSettings.fused_trial)
        if kernels and self.kernels is None:
            raise ValueError("compiled kernels requested, but numba is missing or a term has none")

    # -- pieces of one Newton iteration --------------------------------------
    def energy(self, x, x_prev, x_prev2) -> float:
        """E_total at x (n,3) numpy; Dirichlet handled by elimination, no penalty."""
        if self.kernels is not None:
            return self._inertia_gravity(x, x_prev, x_prev2, _NO_GRADIENT) + self.assembly.energy(x)
        with torch.no_grad():
            e = self.potential(torch.from_numpy(x), torch.from_numpy(x_prev), torch.from_numpy(x_prev2), penalty=False)
        return float(e)

    def _evaluate(self, x, x_prev, x_prev2):
        """E_total at x and, with the compiled kernels, its full gradient (3n,) from the same
        pass (else None: the reference path gets it with the Hessian)."""
        if self.kernels is None:
            return self.energy(x, x_prev, x_prev2), None
        e, grad = self.assembly.energy_gradient(x)
        return e + self._inertia_gravity(x, x_prev, x_prev2, grad), grad

    def _inertia_gravity(self, x, x_prev, x_prev2, grad) -> float:
        """Inertia + gravity energy at x by the compiled kernel; their gradient added into grad (3n,)."""
        c = np.ascontiguousarray
        return float(inertia_gravity(c(x, dtype=np.float64), c(x_prev, dtype=np.float64), c(x_prev2, dtype=np.float64),
                                     self.masses, self.g, 1.0 / self.potential.dt**2, grad))  # fmt: skip

    def _evaluate_hessian(self, x, x_prev, x_prev2, project):
        """E_total at x, its full gradient (3n,) and the free-DoF Hessian, in one pass of the
        compiled kernels (``gradient_hessian``'s, with the energy)."""
        e, grad, U = self.assembly.energy_gradient_hessian(x, self._mass_diagonal, project)
        return e + self._inertia_gravity(x, x_prev, x_prev2, grad), grad, U

    def gradient_hessian(self, x, x_prev, x_prev2, timings=None, project=True):
        """Full gradient (3n,) and the free-DoF Hessian, per-stencil PSD-projected or exact.

        The Hessian is its upper triangle as CSR, or a ``sparse.BandedUpper`` when the compiled
        kernels run and the linear solver is banded (``.tocsr()`` converts).
        """
        if self.kernels is not None:
            return self._gradient_hessian_kernels(x, x_prev, x_prev2, timings, project)
        t0 = time.perf_counter()
        xt = torch.from_numpy(x)
        grads, blocks = [], []
        for term in self.potential.terms:
            g, H = term.local_gradient_hessian(term.gather(xt), project=project)
            grads.append(g.numpy())
            blocks.append(H.numpy())
        t1 = time.perf_counter()
        h2 = self.potential.dt**2
        g_dyn = (self.masses[:, None] / h2 * (x - 2 * x_prev + x_prev2) - self.masses[:, None] * self.g).reshape(-1)
        grad = g_dyn + scatter_gradient(self.n, self.stencils, grads)
        U = self.pattern.assemble(blocks, self.m3 / h2)
        t2 = time.perf_counter()
        if timings is not None:
            timings["local"] += t1 - t0
            timings["assembly"] += t2 - t1
        return grad, U

    def _gradient_hessian_kernels(self, x, x_prev, x_prev2, timings, project):
        """``gradient_hessian`` by the compiled kernels, which add each stencil's gradient and
        Hessian straight into the gradient and the CSR data (timed as 'local', with the mass
        diagonal and the matrix wrapper; 'assembly' is the inertia/gravity gradient)."""
        t0 = time.perf_counter()
        grad, U = self.assembly.gradient_hessian(x, self._mass_diagonal, project)
        t1 = time.perf_counter()
        self._inertia_gravity(x, x_prev, x_prev2, grad)
        t2 = time.perf_counter()
        if timings is not None:
            timings["local"] += t1 - t0
            timings["assembly"] += t2 - t1
        return grad, U

    def _newton_direction(self, x, x_prev, x_prev2, U, gf, tm, info):
        """Solve H dx = -g; with ``hessian='exact_first'`` U is exact and may be indefinite."""
        t0 = time.perf_counter()
        try:
            dx = -self.linear.solve(U, gf)
            if self.settings.hessian == "projected" or _dot(gf, dx) < 0:  # (splu cannot tell SPD from indefinite)
                return dx
        except NotPositiveDefinite:
            if self.settings.hessian != "exact_first":
                raise NewtonFailed("the projected Hessian is not positive definite", np.sqrt(_dot(gf, gf)), info.iterations)
        finally:
            tm["solve"] += time.perf_counter() - t0
        # the exact Hessian is indefinite here: fall back to per-stencil projection
        info.projected += 1
        info.hessians += 1
        _, U = self.gradient_hessian(x, x_prev, x_prev2, tm, project=True)
        t0 = time.perf_counter()
        dx = -self.linear.solve(U, gf)
        tm["solve"] += time.perf_counter() - t0
        return dx

    # -- one time step --------------------------------------------------------
    def step(self, x_prev, x_prev2, dirichlet_targets):
        """Advance one step.

        Parameters
        ----------
        x_prev, x_prev2 : (n,3) positions at t-1 and t-2
        dirichlet_targets : (m,3) prescribed positions x*_D(t)

        Returns
        -------
        x : (n,3), info : StepInfo
        Raises NewtonFailed when the gradient test is not met in max_iterations.
        """
        s = self.settings
        info = StepInfo()
        tm = info.timings
        D = self.dirichlet
        # initial guess: the lowest-energy of the constant-velocity predictor, x_{t-1}, and x_{t-1}
        # carried by the rigid motion that best maps its Dirichlet vertices onto their targets
        # (when the boundary jumps, e.g. reverses, the other two stretch the elements at the boundary)
        candidates = [2 * x_prev - x_prev2, x_prev.copy(), rigidly_carried(x_prev, D, dirichlet_targets)]
        best, e_best = None, np.inf
        t0 = time.perf_counter()
        for c in candidates:
            c[D] = dirichlet_targets
            e = self.energy(c, x_prev, x_prev2)
            if e < e_best:
                best, e_best = c, e
        x = best
        e, grad = self._evaluate(x, x_prev, x_prev2) if self.kernels is not None else (e_best, None)
        tm["guess"] += time.perf_counter() - t0
        tol = s.tolerance * self.f_ref
        project = s.hessian == "projected"
        fused = s.fused_trial and self.kernels is not None
        U_next = None  # the Hessian at x from a fused line-search trial
        for it in range(s.max_iterations + 1):
            # the kernels return the gradient with each energy, so the Hessian is built only
            # when the gradient test fails (the reference path builds both together)
            U, U_next = U_next, None
            if grad is None:
                grad, U = self.gradient_hessian(x, x_prev, x_prev2, tm, project=project)
                info.hessians += 1
            gf = grad[self.free_dofs]
            gnorm = float(np.sqrt(_dot(gf, gf)))
            info.gradient_norm = gnorm
            if not np.isfinite(gnorm):
                raise NewtonFailed(f"non-finite gradient at iteration {it}", gnorm, it)
            if gnorm <= tol:
                info.iterations = self._last_iterations = it
                return x, info
            if it == s.max_iterations:
                break
            if U is None:
                _, U = self.gradient_hessian(x, x_prev, x_prev2, tm, project=project)
                info.hessians += 1
            dx_f = self._newton_direction(x, x_prev, x_prev2, U, gf, tm, info)
            slope = _dot(gf, dx_f)
            if not slope < 0:  # not a descent direction: fall back to steepest descent
                dx_f = -gf / max(U.diagonal().max(), 1e-300)
                slope = _dot(gf, dx_f)
            dx = np.zeros(3 * self.n)
            dx[self.free_dofs] = dx_f
            dx = dx.reshape(-1, 3)
            alpha = 1.0
            t0 = time.perf_counter()
            # Near convergence the predicted decrease drops below what E_total can resolve in
            # float64; Armijo then compares round-off.  Take the full Newton step there.
            resolvable = -slope > s.energy_resolution * max(abs(e), 1e-300)
            fuse = fused and it + 1 < self._last_iterations  # the next iterate is not expected to converge
            fused_s = 0.0  # the fused trial's time, counted as 'local' (a Hessian pass)
            while resolvable:
                x_try = x + alpha * dx
                if fuse and alpha == 1.0:
                    t1 = time.perf_counter()
                    e_try, g_try, U_try = self._evaluate_hessian(x_try, x_prev, x_prev2, project)
                    fused_s = time.perf_counter() - t1
                    info.hessians += 1
                else:
                    e_try, g_try = self._evaluate(x_try, x_prev, x_prev2)
                if np.isfinite(e_try) and e_try <= e + s.armijo * alpha * slope:
                    U_next = U_try if alpha == 1.0 and fuse else None
                    break
                alpha *= 0.5
                if alpha < s.min_step:
                    tm["energy"] += time.perf_counter() - t0 - fused_s
                    tm["local"] += fused_s
                    raise NewtonFailed(
                        f"line search failed at iteration {it} (gradient norm {gnorm:.3e}, tolerance {tol:.3e})",
                        gnorm,
                        it,
                    )
            if not resolvable:
                x_try = x + dx
                e_try, g_try = self._evaluate(x_try, x_prev, x_prev2)
            tm["energy"] += time.perf_counter() - t0 - fused_s
            tm["local"] += fused_s
            x, e, grad = x_try, e_try, g_try
        info.iterations = s.max_iterations
        if s.accept_unconverged:
            return x, info
        raise NewtonFailed(
            f"no convergence in {s.max_iterations} iterations (gradient norm {info.gradient_norm:.3e}, tolerance {tol:.3e})",
            info.gradient_norm,
            s.max_iterations,
        )


def stiffness_matrix(potential: IncrementalPotential, x, free_dofs=None):
    """Elastic Hessian K (full symmetric CSR over ``free_dofs``) at state x (n,3).

    Uses each term's projected per-stencil Hessian; at the rest state the
    elastic Hessian is positive semi-definite, so the projection leaves it
    unchanged there (the use this serves: linear modes and frequencies).
    """
    from latentsim.solve.sparse import symmetric_from_upper

    n = potential.n_vertices
    if free_dofs is None:
        free = np.ones(n, dtype=bool)
        free[potential.dirichlet.cpu().numpy()] = False
        free_dofs = np.flatnonzero(np.repeat(free, 3))
    stencils = [t.stencils.cpu().numpy() for t in potential.terms]
    pattern = HessianPattern(n, stencils, free_dofs)
    xt = torch.as_tensor(np.asarray(x, dtype=np.float64))
    blocks = [t.local_gradient_hessian(t.gather(xt))[1].numpy() for t in potential.terms]
    return symmetric_from_upper(pattern.assemble(blocks, np.zeros(3 * n))).tocsr(), free_dofs


def lowest_modes(potential: IncrementalPotential, k: int, x, free_dofs=None, tol: float = 0.0):
    """The k lowest (omega^2, mode) of K v = omega^2 M v on the free DoFs.

    Sparse shift-invert Lanczos (``eigsh`` about a small negative shift, so that
    K - sigma M is positive definite even where K is singular) on the elastic
    Hessian at ``x`` (n,3) (normally the rest state) and the lumped mass; no
    dense matrix is formed.  The Lanczos start vector is fixed and each mode's
    largest-magnitude entry made positive, so the same inputs give the same
    modes in every process (ARPACK's own start is random).

    Parameters
    ----------
    free_dofs : the DoFs kept; default: all but the potential's Dirichlet set.
    tol : ARPACK's relative accuracy (0: machine precision).

    Returns
    -------
    omega2 : (k,) ascending, modes : (f, k) M-orthonormal, free_dofs : (f,)
    """
    import scipy.sparse
    import scipy.sparse.linalg

    K, free = stiffness_matrix(potential, x, free_dofs)
    m = np.repeat(potential.masses.detach().cpu().numpy().astype(np.float64), 3)[free]
    if k >= len(free) - 1:
        raise ValueError(f"{k} modes asked of a {len(free)}-DoF system")
    sigma = -1e-8 * abs(K.diagonal()).max() / m.max()
    v0 = np.random.default_rng(0).standard_normal(len(free))
    w, V = scipy.sparse.linalg.eigsh(K.tocsc(), k=k, M=scipy.sparse.diags(m).tocsc(), sigma=sigma, which="LM", tol=tol, v0=v0)
    order = np.argsort(w)
    return w[order], fix_sign(V[:, order]), free


def fix_sign(V: np.ndarray) -> np.ndarray:
    """Make each column's largest-magnitude entry positive (eigenvectors have no sign)."""
    idx = np.argmax(np.abs(V), axis=0)
    s = np.sign(V[idx, np.arange(V.shape[1])])
    s[s == 0] = 1.0
    return V * s

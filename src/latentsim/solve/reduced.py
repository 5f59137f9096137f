"""Reduced implicit Euler: the incremental potential minimised over a subspace.

Each time step solves (Fulton et al. 2019, "Latent-space dynamics for reduced
deformable simulation"; with a linear map, classical subspace dynamics)

    q_t = argmin_q  E_total(phi(q, x*_D(t)); x_{t-1}, x_{t-2})

where ``x = phi(q, x*_D)`` maps r reduced coordinates (and the prescribed
Dirichlet positions) to the n vertex positions, and E_total is the scene's
:class:`~latentsim.physics.incremental_potential.IncrementalPotential` - the same object the
full-space solver minimises - plus its Dirichlet penalty when the map does not
impose the boundary conditions exactly.  x_{t-1}, x_{t-2} are the mapped
previous states.

Newton / Gauss-Newton: with J = d phi / d q (3n, r), g and H the full-space
gradient and (per-stencil, optionally PSD-projected) Hessian,

    grad_q = J^T g,      H_q = J^T H J        (Gauss-Newton: drops g . d2 phi / dq2,
                                                exact for a linear map)

a dense r x r Cholesky solve, Armijo backtracking on E_total(phi(q)), and a
stop when the full-space gradient projected onto the tangent space of the
subspace, ||Q^T g|| (J = QR), is at most ``tolerance * f_ref`` - for a map
spanning all free DoFs this is exactly the full solver's test.  L-BFGS
(two-loop recursion preconditioned by the reduced mass matrix J^T M J / h^2)
is the Hessian-free alternative.

Where a term of the potential turns infinite somewhere (a barrier against colliders: its
``first_impact``) every iterate stays where all are finite, as in the full space: an initial guess counts
only where the straight path to it from x_{t-1} does (and x_{t-1}'s own projection is tried where
neither other guess's does); the line search starts from the terms' first impact along the step's
tangent J dq (exact for a linear map), and for a nonlinear map rejects a trial whose chord from the
iterate crosses one.  Testing only where a step lands lets a step jump through a thin collider, and
from a guess of infinite energy (inside one) no later decrease is resolvable.

The full-space gradient and Hessian come from :class:`latentsim.solve.implicit_euler.ImplicitEuler`
(the compiled assembly of :mod:`latentsim.solve.assembly`); physics is not re-implemented here.
Both minimisers run the one Newton loop and line search of :mod:`latentsim.solve.newton`.

A subspace is any object with ``dim``, ``n_vertices``, ``hard_dirichlet``,
``dirichlet`` and ``jacobian(q, xD) -> (x (n, 3), J (3n, r))`` /
``map(q, xD) -> x`` (with a barrier also ``project(x, xD) -> q``, and ``linear`` True where
phi is linear in q): :class:`~latentsim.latent.subspaces.LinearSubspace` (x = X + U q in the
relative coordinates) and :class:`~latentsim.latent.subspaces.DecoderSubspace` (the autoencoder's
decoder), re-exported here.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from latentsim.physics.incremental_potential import IncrementalPotential, dirichlet_penalty
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings
from latentsim.solve.newton import LineSearch, first_impact, max_step, minimise

__all__ = [
    "ReducedFailed",
    "ReducedImplicitEuler",
    "ReducedSettings",
    "ReducedStepInfo",
    "reduced_rollout",
]


TIMING_PARTS = ("map", "derivatives", "reduce", "line_search")


class ReducedFailed(RuntimeError):
    """A reduced step did not converge (or met a non-finite value)."""

    def __init__(self, message, info=None):
        super().__init__(message)
        self.info = info


# ---------------------------------------------------------------------------
# the reduced solver
# ---------------------------------------------------------------------------
@dataclass
class ReducedSettings:
    """Settings of the per-step reduced solve.

    ``method``: ``newton`` or ``lbfgs``.  ``map_curvature``: Newton adds the
    map's second-derivative term sum_i g_i d^2 phi_i / dq^2 where the subspace
    provides it (``curvature``) and the sum stays positive definite, else takes
    the Gauss-Newton step on J^T H J (exact for linear maps).  ``hessian``: ``exact_first`` (exact per-stencil Hessians while
    the reduced matrix is positive definite, projected otherwise) or
    ``projected``.  ``tolerance`` is relative to the solver's force scale (as
    in :class:`latentsim.solve.implicit_euler.NewtonSettings`).  ``penalty``: Dirichlet
    penalty in E_total; None -> on unless the subspace imposes it exactly.
    """

    method: str = "newton"
    tolerance: float = 1e-6
    max_iterations: int = 50
    hessian: str = "exact_first"
    armijo: float = 1e-4
    energy_resolution: float = 1e-12
    min_step: float = 1e-10
    lbfgs_memory: int = 8
    penalty: bool | None = None
    map_curvature: bool = True

    def __post_init__(self):
        if self.method not in ("newton", "lbfgs"):
            raise ValueError(f"reduced method '{self.method}': use 'newton' or 'lbfgs'")
        if self.hessian not in ("exact_first", "projected"):
            raise ValueError(f"reduced hessian '{self.hessian}': use 'exact_first' or 'projected'")


@dataclass
class ReducedStepInfo:
    """How one reduced step went: iterations, final tangent-gradient norm, the
    energy after every iteration (``energies[0]`` at the initial guess)."""

    iterations: int = 0
    gradient_norm: float = float("nan")
    converged: bool = False
    projected: int = 0
    gauss_newton: int = 0  # iterations where J^T H J + the map's curvature was indefinite
    energies: list = field(default_factory=list)
    # wall seconds: the map and its Jacobian, full-space gradient + Hessian, the reduction
    # J^T g, J^T H J and the solve, the line search (map + energy)
    timings: dict = field(default_factory=lambda: {"map": 0.0, "derivatives": 0.0, "reduce": 0.0, "line_search": 0.0})


class ReducedImplicitEuler:
    """Implicit Euler in a subspace ``x = phi(q, x*_D)``.

    Parameters
    ----------
    subspace : :class:`~latentsim.latent.subspaces.LinearSubspace`, :class:`~latentsim.latent.subspaces.DecoderSubspace` or any object
        with the same attributes and ``jacobian``/``map``.
    potential : the scene's IncrementalPotential with *every* elastic stencil
        (``build_potential(..., free_only=False)``, as ``potential_from_artefact``
        gives) when the subspace moves Dirichlet vertices (``mean`` coordinates).
    settings : :class:`ReducedSettings`.
    solver_options : keyword arguments for the internal
        :class:`latentsim.solve.implicit_euler.ImplicitEuler` that evaluates gradients and
        Hessians (e.g. its ``threads``).
    """

    def __init__(self, subspace, potential: IncrementalPotential, settings: ReducedSettings | None = None, solver_options=None):
        self.subspace = subspace
        self.potential = potential
        self.settings = settings or ReducedSettings()
        self.penalty = (not subspace.hard_dirichlet) if self.settings.penalty is None else bool(self.settings.penalty)
        D = potential.dirichlet.cpu().numpy().astype(np.int64)
        if subspace.hard_dirichlet:
            if not np.array_equal(np.sort(np.asarray(subspace.dirichlet)), np.sort(D)):
                raise ValueError("the subspace prescribes other Dirichlet vertices than the potential")
            inner = potential  # the Dirichlet DoFs never move: eliminate them as the full solver does
        else:  # every DoF may move: the gradient and Hessian over all of them, the penalty added here
            inner = dataclasses.replace(potential, dirichlet=torch.zeros(0, dtype=torch.long))
        self.D = D
        self.inner = ImplicitEuler(inner, NewtonSettings(), **(solver_options or {}))
        self.rows = self.inner.free_dofs  # DoFs the subspace may move
        self.w_bc = float(potential.w_bc)
        free_v = np.ones(potential.n_vertices, dtype=bool)
        free_v[D] = False
        m = self.inner.masses
        # force scale of the convergence test: that of the full solver of this scene
        self.f_ref = float(np.linalg.norm(m[free_v]) * max(np.linalg.norm(self.inner.g), 1.0))
        self._Ddofs = (3 * D[:, None] + np.arange(3)).reshape(-1)
        self._tm = ReducedStepInfo().timings  # where _reduced_system adds its time (the step's info)

    # -- E_total and its derivatives along the subspace -------------------------
    def energy(self, x, x_prev, x_prev2, xD) -> float:
        """E_total(x) (+ the Dirichlet penalty where the subspace does not impose it)."""
        e = self.inner.energy(x, x_prev, x_prev2)
        if self.penalty and len(self.D):
            with torch.no_grad():
                e += float(dirichlet_penalty(torch.from_numpy(x), torch.from_numpy(self.D), torch.from_numpy(np.asarray(xD, dtype=np.float64)), self.w_bc))
        return e

    def full_gradient(self, x, xD, grad):
        """Add the penalty's gradient 2 w_bc (x_D - x*_D) (of ``dirichlet_penalty``) to grad (3n,)."""
        if self.penalty and len(self.D):
            grad[self._Ddofs] += 2.0 * self.w_bc * (x[self.D] - xD).reshape(-1)
        return grad

    def reduced_gradient(self, q, x_prev, x_prev2, xD):
        """(E, dE/dq (r,), x) at q, by the terms' per-stencil gradients and J^T g."""
        x, J = self.subspace.jacobian(q, xD)
        grad, _ = self.inner.gradient_hessian(x, x_prev, x_prev2, project=True)
        self.full_gradient(x, xD, grad)
        return self.energy(x, x_prev, x_prev2, xD), J.T @ grad, x

    def _reduced_system(self, x, J, x_prev, x_prev2, xD, project):
        """g_q = J^T g and H_q = J^T H J over the moving DoFs (+ the penalty's 2 w_bc J_D^T J_D)."""
        t0 = time.perf_counter()
        grad, U = self.inner.gradient_hessian(x, x_prev, x_prev2, project=project)
        self._tm["derivatives"] += time.perf_counter() - t0
        U = U.tocsr()  # the solver may hand back its banded storage
        self.full_gradient(x, xD, grad)
        Jf = J[self.rows]
        HJ = U @ Jf + U.T @ Jf - U.diagonal()[:, None] * Jf  # U holds the upper triangle
        Hq = Jf.T @ HJ
        if self.penalty and len(self.D):
            JD = J[self._Ddofs]
            Hq += 2.0 * self.w_bc * (JD.T @ JD)
        return grad, J.T @ grad, 0.5 * (Hq + Hq.T)

    def _converged(self, J, grad, tol, info) -> bool:
        """Records ||P g|| (P = J (J^T J)^+ J^T: the full-space gradient projected onto the
        subspace's tangent space) in ``info`` and tests it against ``tol``.

        ||P g||^2 = g_q^T (J^T J)^+ g_q with g_q = J^T g: an r x r pseudo-inverse
        instead of a QR of the (3n, r) Jacobian."""
        gq = J.T @ grad
        lam, V = np.linalg.eigh(J.T @ J)
        keep = lam > 1e-12 * max(float(lam[-1]), 1e-300)
        c = V[:, keep].T @ gq
        info.gradient_norm = gn = float(np.sqrt(max(float(c @ (c / lam[keep])), 0.0)))
        if not np.isfinite(gn):
            raise ReducedFailed(f"non-finite gradient at iteration {info.iterations}", info)
        info.converged = gn <= tol
        return info.converged

    def energy_gradient(self, x, x_prev, x_prev2, xD):
        """E_total and its full-space gradient (3n,) by autograd of the potential (no Hessian)."""
        xt = torch.from_numpy(np.array(x, dtype=np.float64)).requires_grad_(True)
        e = self.potential(
            xt, torch.from_numpy(np.asarray(x_prev)), torch.from_numpy(np.asarray(x_prev2)),
            targets=torch.from_numpy(np.asarray(xD, dtype=np.float64)), penalty=self.penalty,
        )
        (g,) = torch.autograd.grad(e, xt)
        return float(e.detach()), g.numpy().reshape(-1)

    def _best_guess(self, candidates, frame, xD, energies):
        """(q, x, E) of the lowest-energy of ``candidates`` (q's) whose energy is finite and whose straight path
        from the ``frame``'s x_{t-1} keeps every term finite (every vertex outside the colliders, as the attached
        ones move); None if none is.  Appends each one's energy (inf where its path crosses a collider) to ``energies``."""
        best, x_prev, x_prev2 = None, frame.x_prev, frame.x_prev2
        for c in candidates:
            c = np.asarray(c, dtype=np.float64)
            x = self.subspace.map(c, xD)
            if not first_impact(self.inner.frame_terms, x_prev, x - x_prev, frame) > 1.0:
                energies.append(np.inf)
                continue
            e = self.energy(x, x_prev, x_prev2, xD)
            energies.append(e)
            if np.isfinite(e) and (best is None or e < best[2]):
                best = (c, x, e)
        return best

    def step(self, q_prev, q_prev2, x_prev, x_prev2, xD, q_init=None):
        """Advance one step.

        Parameters
        ----------
        q_prev, q_prev2 : (r,) reduced coordinates at t-1, t-2 (initial guesses).
        x_prev, x_prev2 : (n, 3) positions at t-1, t-2 (normally their maps).
        xD : (m, 3) prescribed Dirichlet positions at t.
        q_init : optional initial guess (else the lower-energy of q_{t-1} and 2 q_{t-1} - q_{t-2}).

        Returns
        -------
        q (r,), x (n, 3), :class:`ReducedStepInfo`.  Raises :class:`ReducedFailed`
        when the test is not met in ``max_iterations``, a value is non-finite, or every
        initial guess has a non-finite energy (or a path from x_{t-1} through a collider).
        """
        xD, x_prev = np.asarray(xD, dtype=np.float64), np.asarray(x_prev, dtype=np.float64)
        frame = self.inner.frame(x_prev, x_prev2, xD, x_prev[self.D])  # the prescribed vertices then: the potential's
        self.inner.begin_step(frame)  # attached colliders where this step's targets put them; friction lagged from x_prev
        q_prev, q_prev2 = np.asarray(q_prev, dtype=np.float64), np.asarray(q_prev2, dtype=np.float64)
        candidates = [q_init] if q_init is not None else [2.0 * q_prev - q_prev2, q_prev]
        limited, energies = self.inner.limits_steps, []
        best = self._best_guess(candidates, frame, xD, energies)
        if best is None and limited and q_init is None:
            # neither guess's path stays outside: x_{t-1} left where it is, as near as the subspace comes (as the
            # full space's guesses; a body its prescribed vertices carry towards a collider it rests on)
            best = self._best_guess([self.subspace.project(x_prev, xD)], frame, xD, energies)
        if best is None:  # from a guess of infinite energy no step length is ever resolvably worse: never start there
            raise ReducedFailed("every initial guess has a non-finite energy ("
                                + ("inf also where its path from x_{t-1} crosses a collider: " if limited else "")
                                + ", ".join(f"{e:.3e}" for e in energies) + ")", ReducedStepInfo())
        q, x, e = best
        info = ReducedStepInfo(energies=[e])
        self._tm = info.timings
        s = self.settings
        problem = (_LbfgsProblem if s.method == "lbfgs" else _NewtonProblem)(self, x_prev, x_prev2, xD, info)
        q, result = minimise(problem, q, e, LineSearch(s.armijo, s.min_step, s.energy_resolution), s.max_iterations)
        if result.stopped:
            return q, problem.x, info
        raise ReducedFailed(f"{problem.name}no convergence in {s.max_iterations} iterations "
                            f"(tangent gradient {info.gradient_norm:.3e}, tolerance {problem.tol:.3e})", info)  # fmt: skip


class _ReducedProblem:
    """One reduced step as the problem of :func:`latentsim.solve.newton.minimise` over q: trials
    map q and evaluate E_total(phi(q)); a failed line search raises :class:`ReducedFailed`."""

    name = ""  # the method, in front of the no-convergence message

    def __init__(self, solver: ReducedImplicitEuler, x_prev, x_prev2, xD, info: ReducedStepInfo):
        self.solver, self.x_prev, self.x_prev2, self.xD, self.info = solver, x_prev, x_prev2, xD, info
        self.tol = solver.settings.tolerance * solver.f_ref
        self.x = None  # phi(q) at the last stop()

    def trial(self, q, alpha, searching):
        x = self.solver.subspace.map(q, self.xD)
        # the straight path from the iterate passes where a term is infinite (through a collider): rejected, as
        # inside one (for a linear map max_step has kept every trial's path outside already)
        if not getattr(self.solver.subspace, "linear", False) and not first_impact(self.solver.inner.step_terms, self.x, x - self.x) > 1.0:
            return np.inf, x
        return self.solver.energy(x, self.x_prev, self.x_prev2, self.xD), x

    def max_step(self, q, dq) -> float:
        """The step terms' :func:`~latentsim.solve.newton.max_step` along x + t J dq (x = phi(q) and J from the
        last ``stop``): the step fraction that keeps every vertex outside the colliders, exact for a linear map
        (for a decoder the trial tests each chord it takes); 1 where no term limits it."""
        terms = self.solver.inner.step_terms
        return max_step(terms, self.x, (self.J @ dq).reshape(-1, 3)) if self.solver.inner.limits_steps else 1.0

    def accept(self, trial, e_old, seconds):
        self.info.energies.append(trial.energy)

    def line_search_failed(self, it, seconds):
        raise ReducedFailed(f"line search failed at iteration {it}", self.info)


class _NewtonProblem(_ReducedProblem):
    """Newton on J^T H J (+ the map's curvature where it keeps the matrix positive definite), a
    dense Cholesky solve; the exact Hessian falls back to the projected one."""

    def stop(self, q, it) -> bool:
        sv, info = self.solver, self.info
        info.iterations = it
        t0 = time.perf_counter()
        self.x, self.J = sv.subspace.jacobian(q, self.xD)
        self.t1 = time.perf_counter()
        info.timings["map"] += self.t1 - t0
        self.d0 = info.timings["derivatives"]
        project = sv.settings.hessian == "projected"
        self.grad, self.gq, self.Hq = sv._reduced_system(self.x, self.J, self.x_prev, self.x_prev2, self.xD, project=project)
        return sv._converged(self.J, self.grad, self.tol, info)

    def direction(self, q, it):
        sv, s, info = self.solver, self.solver.settings, self.info
        gq, Hq = self.gq, self.Hq
        L = None
        if s.map_curvature and hasattr(sv.subspace, "curvature"):
            # the full gradient does not vanish at a reduced minimum, so the map's
            # curvature matters: without it Gauss-Newton converges only linearly
            try:
                L = np.linalg.cholesky(Hq + sv.subspace.curvature(q, self.xD, self.grad))
            except np.linalg.LinAlgError:
                info.gauss_newton += 1
        try:
            L = L if L is not None else np.linalg.cholesky(Hq)
        except np.linalg.LinAlgError:
            if s.hessian == "projected":
                raise ReducedFailed("the reduced projected Hessian is not positive definite", info) from None
            info.projected += 1
            _, gq, Hq = sv._reduced_system(self.x, self.J, self.x_prev, self.x_prev2, self.xD, project=True)
            L = np.linalg.cholesky(Hq + 1e-12 * np.trace(Hq) / len(Hq) * np.eye(len(Hq)))
        dq = -np.linalg.solve(L.T, np.linalg.solve(L, gq))
        slope = float(gq @ dq)
        info.timings["reduce"] += time.perf_counter() - self.t1 - (info.timings["derivatives"] - self.d0)
        return dq, slope

    def accept(self, trial, e_old, seconds):
        super().accept(trial, e_old, seconds)
        self.info.timings["line_search"] += seconds


class _LbfgsProblem(_ReducedProblem):
    """L-BFGS (two-loop recursion) with the reduced mass matrix J^T M J / h^2 as initial Hessian."""

    name = "L-BFGS: "

    def __init__(self, solver, x_prev, x_prev2, xD, info):
        super().__init__(solver, x_prev, x_prev2, xD, info)
        self.h2 = solver.potential.dt ** 2
        self.m3 = np.repeat(solver.inner.masses, 3)
        self.hist: list = []
        self.g_old = self.q_old = None
        self.H0 = None

    def stop(self, q, it) -> bool:
        sv, info = self.solver, self.info
        info.iterations = it
        self.x, self.J = sv.subspace.jacobian(q, self.xD)
        grad = sv.energy_gradient(self.x, self.x_prev, self.x_prev2, self.xD)[1]
        self.gq = self.J.T @ grad
        return sv._converged(self.J, grad, self.tol, info)

    def direction(self, q, it):
        solver, J, gq = self.solver, self.J, self.gq
        if self.H0 is None:
            M0 = (J * (self.m3 / self.h2)[:, None]).T @ J
            if solver.penalty and len(solver.D):
                JD = J[solver._Ddofs]
                M0 += 2.0 * solver.w_bc * (JD.T @ JD)
            self.H0 = np.linalg.cholesky(M0 + 1e-12 * np.trace(M0) / len(M0) * np.eye(len(M0)))
        H0 = self.H0
        if self.g_old is not None:
            s_k, y_k = q - self.q_old, gq - self.g_old
            if s_k @ y_k > 1e-12 * np.linalg.norm(s_k) * np.linalg.norm(y_k):
                self.hist.append((s_k, y_k, 1.0 / (s_k @ y_k)))
                self.hist = self.hist[-solver.settings.lbfgs_memory:]
        d = gq.copy()
        alphas = []
        for s_k, y_k, rho in reversed(self.hist):
            a = rho * (s_k @ d)
            alphas.append(a)
            d -= a * y_k
        d = np.linalg.solve(H0.T, np.linalg.solve(H0, d))
        for (s_k, y_k, rho), a in zip(self.hist, reversed(alphas)):
            d += s_k * (a - rho * (y_k @ d))
        dq = -d
        slope = float(gq @ dq)
        if not slope < 0:
            self.hist.clear()
            dq = -np.linalg.solve(H0.T, np.linalg.solve(H0, gq))
            slope = float(gq @ dq)
        self.q_old, self.g_old = q, gq
        return dq, slope


# ---------------------------------------------------------------------------
# rollout
# ---------------------------------------------------------------------------
def reduced_rollout(subspace, potential, q0, q1, dirichlet_positions, settings: ReducedSettings | None = None, solver=None, solver_options=None) -> dict:
    """Reduced implicit-Euler rollout from the reduced coordinates of frames 0 and 1.

    Parameters
    ----------
    subspace, potential, settings, solver_options : as :class:`ReducedImplicitEuler`
        (or pass a ready ``solver``).
    q0, q1 : (r,) reduced coordinates of frames 0 and 1.
    dirichlet_positions : (T, m, 3) prescribed positions x*_D(t).

    Returns
    -------
    dict with ``positions`` (T, n, 3) float64 (the layout of
    :func:`latentsim.latent.rollout`; NaN from the frame whose solve failed on), ``latents`` (T, r),
    ``step_ms`` (T,) (wall time of each step's solve; NaN at frames 0, 1),
    ``iterations`` (T,) int, ``gradient_norm`` (T,), ``diverged_frame`` (first
    frame that met a non-finite value or did not converge; -1 if none), ``failure``
    (why that frame's step failed; "" if none), and the
    step's split ``map_ms``, ``derivatives_ms``, ``reduce_ms``, ``line_search_ms`` (T,)
    (see :class:`ReducedStepInfo`; Newton only).
    """
    solver = solver or ReducedImplicitEuler(subspace, potential, settings, solver_options)
    xD = np.asarray(dirichlet_positions, dtype=np.float64)
    T, r = xD.shape[0], subspace.dim
    Q = np.full((T, r), np.nan)
    X = np.full((T, subspace.n_vertices, 3), np.nan)
    ms = np.full(T, np.nan)
    iters = np.zeros(T, dtype=np.int64)
    gnorm = np.full(T, np.nan)
    parts = np.full((T, 4), np.nan)
    Q[0], Q[1] = q0, q1
    X[0], X[1] = subspace.map(Q[0], xD[0]), subspace.map(Q[1], xD[1])
    diverged, failure = -1, ""
    for t in range(2, T):
        t0 = time.perf_counter()
        try:
            q, x, info = solver.step(Q[t - 1], Q[t - 2], X[t - 1], X[t - 2], xD[t])
        except (ReducedFailed, np.linalg.LinAlgError, FloatingPointError) as err:
            ms[t] = 1e3 * (time.perf_counter() - t0)
            info = getattr(err, "info", None)
            if info is not None:
                iters[t], gnorm[t] = info.iterations, info.gradient_norm
            diverged, failure = t, f"{type(err).__name__}: {err}"
            break
        ms[t] = 1e3 * (time.perf_counter() - t0)
        iters[t], gnorm[t] = info.iterations, info.gradient_norm
        parts[t] = [1e3 * info.timings[k] for k in TIMING_PARTS]
        Q[t], X[t] = q, x
        if not (np.isfinite(q).all() and np.isfinite(x).all()):
            diverged, failure = t, "non-finite reduced coordinates or positions"
            break
    return {
        "positions": X, "latents": Q, "step_ms": ms, "iterations": iters, "gradient_norm": gnorm,
        "diverged_frame": int(diverged), "failure": failure, **{f"{k}_ms": parts[:, i] for i, k in enumerate(TIMING_PARTS)},
    }

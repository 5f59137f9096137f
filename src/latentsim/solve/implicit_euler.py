"""Full-space implicit Euler: Newton's method on the incremental potential.

Each time step solves (Martin et al. 2011; Li et al. 2025, Eq. 1)

    x_t = argmin_x  E_total(x; x_{t-1}, x_{t-2})   s.t.  x_D = x*_D(t)

with Newton's method: per-stencil Hessians projected to positive semi-definite
(Teran et al. 2005) and assembled over the free DoFs only (Dirichlet DoFs are
removed from the system and set to their prescribed values), a sparse SPD
solve, and a backtracking (Armijo) line search on E_total (the one Newton loop of
:mod:`latentsim.solve.newton`).  A step has
converged when the 2-norm of the free-DoF gradient is at most
``tolerance * f_ref``, with ``f_ref`` the weight of the free vertices
(||m|| max(|g|, 1 m/s^2)), so the tolerance is a relative force residual.

The potential's terms that depend on the step (its ``frame_terms``: a contact barrier, a damping
term) are evaluated as they stand over each step (``EnergyTerm.at`` its
:class:`~latentsim.physics.frame.Frame`), and the line search starts short of where one turns
infinite (:func:`latentsim.solve.newton.max_step`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from latentsim.physics.frame import Frame
from latentsim.physics.incremental_potential import IncrementalPotential
from latentsim.physics.kernels import inertia_gravity
from latentsim.solve.assembly import CompiledAssembly
from latentsim.solve.newton import LineSearch, first_impact, max_step, minimise
from latentsim.solve.sparse import HessianPattern, LinearSolver, NotPositiveDefinite


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
    # the line search's full-step trial is one pass for energy, gradient
    # and Hessian while the step is not expected to converge (iteration k + 1 < the previous
    # frame's iteration count); an accepted step then needs no second pass over the stencils (a
    # rejected trial, or one that converges earlier than the previous frame did, leaves its
    # Hessian unused)
    fused_trial: bool = True
    min_step: float = 1e-10

    def __post_init__(self):
        if self.hessian not in ("projected", "exact_first"):
            raise ValueError(f"newton.hessian '{self.hessian}': use 'projected' or 'exact_first'")


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


def _non_finite(name: str, a) -> str | None:
    """None when every entry of the array ``a`` is finite; else a description naming ``name``, the
    count of non-finite entries and the first one (its index and value)."""
    a = np.asarray(a, dtype=np.float64)
    bad = ~np.isfinite(a)
    if not bad.any():
        return None
    first = np.unravel_index(int(np.argmax(bad)), a.shape) if a.ndim else ()
    where = f" (first at index {tuple(int(i) for i in first)}: {a[first]})" if a.ndim else f" ({float(a)})"
    return f"{name} has {int(bad.sum())} non-finite of {a.size} entries{where}"


def check_finite_potential(potential: IncrementalPotential) -> None:
    """Raise ValueError naming the quantity when the time step, the masses, gravity, or a material
    constant of one of the potential's terms (any floating tensor or number among its attributes:
    stiffnesses, Lame parameters, rest lengths, ...) is NaN or infinite; a non-finite value there
    would otherwise surface deep inside the compiled kernels (a numba TypingError, or an SVD that
    does not converge)."""
    problems = [
        _non_finite("the time step dt", float(potential.dt)),
        _non_finite("the masses", potential.masses.detach().cpu().numpy()),
        _non_finite("gravity g", potential.g.detach().cpu().numpy()),
    ]
    for term in potential.terms:
        for key, value in vars(term).items():
            if torch.is_tensor(value) and value.is_floating_point():
                problems.append(_non_finite(f"term {term.name!r}: {key}", value.detach().cpu().numpy()))
            elif isinstance(value, float):
                problems.append(_non_finite(f"term {term.name!r}: {key}", value))
    problems = [q for q in problems if q]
    if problems:
        raise ValueError("the incremental potential is not finite (check the material constants, dt and gravity): " + "; ".join(problems))
    if not float(potential.dt) > 0:
        raise ValueError(f"the incremental potential's time step dt must be > 0, got {float(potential.dt)}")


def rigidly_carried(x, D, targets):
    """x (n,3) moved by the rigid motion best mapping x[D] onto targets (Kabsch; translation if m < 3;
    x itself, a copy, without Dirichlet vertices)."""
    if len(D) == 0:
        return np.array(x, dtype=np.float64)
    src = x[D]
    cs, ct = src.mean(axis=0), np.asarray(targets).mean(axis=0)
    if len(D) < 3:
        return x + (ct - cs)
    U, _, Vt = np.linalg.svd((src - cs).T @ (targets - ct))
    d = np.sign(np.linalg.det(U @ Vt))
    R = (U @ np.diag([1.0, 1.0, d]) @ Vt).T
    return np.einsum("ij,kj->ik", x - cs, R) + ct


class ImplicitEuler:
    """Newton solver for one scene's incremental potential.

    Parameters
    ----------
    potential : IncrementalPotential (terms, masses, dt, g, dirichlet)
    settings : NewtonSettings
    threads : 1 or 2 threads for the compiled kernels (two vertex-disjoint halves of each
        term's stencils run concurrently, ``latentsim.physics.kernels.split_stencils``; the
        result is the same either way); default ``min(2, torch.get_num_threads())``,
        the budget a pipeline stage sets from its rule's ``threads``.
    """

    def __init__(self, potential: IncrementalPotential, settings: NewtonSettings | None = None, threads: int | None = None):
        check_finite_potential(potential)
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
        self.frame_terms = list(getattr(potential, "frame_terms", ()))
        # their blocks too (a reduced solver's cubature terms may not touch every vertex)
        self.pattern = HessianPattern(n, self.stencils + [t.stencils.cpu().numpy() for t in self.frame_terms], self.free_dofs)
        self.linear = LinearSolver(self.pattern, self.settings.linear_solver, dynamic=any(getattr(t, "dynamic", False) for t in self.frame_terms))
        m_free = self.masses[free_v]
        self.f_ref = float(np.linalg.norm(m_free) * max(np.linalg.norm(self.g), 1.0))
        self.m3 = np.repeat(self.masses, 3)
        self._mass_diagonal = self.m3 / potential.dt**2  # the inertia's Hessian, M / h^2
        self.assembly = CompiledAssembly.of(
            potential.terms, self.pattern, n, self.linear.method == "banded", min(2, int(threads or torch.get_num_threads()))
        )
        self.assembly.with_frame_terms(self.frame_terms)
        self.step_terms = self.frame_terms  # as they stand over the current step (begin_step)
        self._last_iterations = 0  # the previous step's Newton iterations (NewtonSettings.fused_trial)

    @property
    def limits_steps(self) -> bool:
        """Whether a term of the potential turns infinite somewhere (has a ``first_impact``: a barrier)."""
        return any(hasattr(t, "first_impact") for t in self.frame_terms)

    # -- E_total and its derivatives ------------------------------------------
    def energy(self, x, x_prev, x_prev2) -> float:
        """E_total at x (n,3) numpy; Dirichlet handled by elimination, no penalty."""
        return self._inertia_gravity(x, x_prev, x_prev2, _NO_GRADIENT) + self.assembly.energy(x)

    def _evaluate(self, x, x_prev, x_prev2):
        """E_total at x and its full gradient (3n,), in one pass."""
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

        The compiled kernels add each stencil's gradient and Hessian straight into the gradient
        and the matrix data (timed as 'local', with the mass diagonal and the matrix wrapper;
        'assembly' is the inertia/gravity gradient).  The Hessian is its upper triangle as CSR,
        or a ``sparse.BandedUpper`` when the linear solver is banded (``.tocsr()`` converts).
        """
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
    def frame(self, x_prev, x_prev2, dirichlet_targets, previous_targets=None) -> Frame:
        """The frame of the step from ``x_prev``, ``x_prev2`` (n, 3) to the prescribed ``dirichlet_targets``
        (m, 3); the prescribed vertices at its start ``previous_targets`` (by default x_prev's own)."""
        before = np.asarray(x_prev)[self.dirichlet] if previous_targets is None else previous_targets
        return Frame(dirichlet_targets, x_prev, x_prev2, before, float(self.potential.dt))

    def begin_step(self, frame: Frame):
        """Set the terms of the step of ``frame`` (``EnergyTerm.at``): the energy, its derivatives and the line
        search of what follows see them.  :meth:`step` calls it; a solver that steps otherwise (a reduced one)
        calls it per step."""
        self.step_terms = [t.at(frame) for t in self.frame_terms]
        self.assembly.step_terms = self.step_terms

    def initial_guess(self, x_prev, x_prev2, dirichlet_targets, frame=None):
        """The lowest-energy of the constant-velocity predictor, x_{t-1}, and x_{t-1} carried by
        the rigid motion that best maps its Dirichlet vertices onto their targets (when the
        boundary jumps, e.g. reverses, the other two stretch the elements at the boundary);
        each with x_D = x*_D(t), and each only where its straight path from x_{t-1} keeps every term finite
        (:func:`~latentsim.solve.newton.first_impact` over ``frame``, by default :meth:`frame`'s).  Returns x (n,3).

        Raises NewtonFailed when an input is not finite, or when every candidate's energy is
        (the message names the inputs' first non-finite entry, or the candidates' energies).
        """
        problems = [_non_finite(k, v) for k, v in (("x_{t-1}", x_prev), ("x_{t-2}", x_prev2), ("the Dirichlet targets", dirichlet_targets))]
        problems = [q for q in problems if q]
        if problems:
            raise NewtonFailed("non-finite input to the step: " + "; ".join(problems))
        D = self.dirichlet
        frame = self.frame(x_prev, x_prev2, dirichlet_targets) if frame is None else frame
        candidates = [2 * x_prev - x_prev2, x_prev.copy(), rigidly_carried(x_prev, D, dirichlet_targets)]
        best, e_best, energies = None, np.inf, []
        for c in candidates:
            c[D] = dirichlet_targets
            if not first_impact(self.frame_terms, x_prev, c - x_prev, frame) > 1.0:
                energies.append(np.inf)  # its path from x_{t-1} passes where a term is infinite (through a collider, as the attached ones move)
                continue
            e = self.energy(c, x_prev, x_prev2)
            energies.append(e)
            if np.isfinite(e) and e < e_best:
                best, e_best = c, e
        if best is None:
            names = ("constant velocity", "x_{t-1}", "rigidly carried")
            raise NewtonFailed(
                "every initial guess has a non-finite energy ("
                + ("inf also where its path from x_{t-1} crosses a collider; " if self.limits_steps else "")
                + ", ".join(f"{k}: {e:.3e}" for k, e in zip(names, energies))
                + "): the state or the potential is not finite"
            )
        return best

    def step(self, x_prev, x_prev2, dirichlet_targets):
        """Advance one step.

        Parameters
        ----------
        x_prev, x_prev2 : (n,3) positions at t-1 and t-2
        dirichlet_targets : (m,3) prescribed positions x*_D(t)

        Returns
        -------
        x : (n,3), info : StepInfo

        Raises
        ------
        NewtonFailed : the gradient test is not met in max_iterations; an input is not finite;
            every initial guess has a non-finite energy; the gradient becomes non-finite.
        """
        s = self.settings
        info = StepInfo()
        t0 = time.perf_counter()
        frame = self.frame(x_prev, x_prev2, dirichlet_targets)
        self.begin_step(frame)
        x = self.initial_guess(x_prev, x_prev2, dirichlet_targets, frame)
        e, grad = self._evaluate(x, x_prev, x_prev2)
        info.timings["guess"] += time.perf_counter() - t0
        problem = _StepProblem(self, x_prev, x_prev2, grad, info)
        search = LineSearch(s.armijo, s.min_step, s.energy_resolution)
        x, result = minimise(problem, x, e, search, s.max_iterations)
        info.iterations = result.iterations
        if result.stopped:
            self._last_iterations = result.iterations
            return x, info
        if s.accept_unconverged:
            return x, info
        raise NewtonFailed(
            f"no convergence in {s.max_iterations} iterations (gradient norm {info.gradient_norm:.3e}, tolerance {problem.tol:.3e})",
            info.gradient_norm,
            s.max_iterations,
        )


class _StepProblem:
    """One time step as the problem of :func:`latentsim.solve.newton.minimise`: the gradient
    test on the free DoFs, the sparse Newton direction, trials by the compiled kernels (the
    full-step trial also building the next Hessian where ``fused_trial`` says so)."""

    def __init__(self, solver: ImplicitEuler, x_prev, x_prev2, grad, info: StepInfo):
        s = solver.settings
        self.solver, self.x_prev, self.x_prev2, self.info = solver, x_prev, x_prev2, info
        self.tol = s.tolerance * solver.f_ref
        self.project = s.hessian == "projected"
        self.grad, self.U, self.U_next = grad, None, None  # the gradient at x; the Hessian from a fused trial
        self.fuse = False  # this iteration's full-step trial also builds the Hessian
        self.fused_seconds = 0.0  # the fused trial's time, counted as 'local' (a Hessian pass)

    def stop(self, x, it) -> bool:
        info = self.info
        self.U, self.U_next = self.U_next, None
        gf = self.gf = self.grad[self.solver.free_dofs]
        gnorm = float(np.sqrt(_dot(gf, gf)))
        info.gradient_norm = gnorm
        if not np.isfinite(gnorm):
            raise NewtonFailed(f"non-finite gradient at iteration {it} (gradient norm {gnorm})", gnorm, it)
        return gnorm <= self.tol

    def direction(self, x, it):
        sv, info, tm, gf = self.solver, self.info, self.info.timings, self.gf
        U = self.U
        if U is None:
            _, U = sv.gradient_hessian(x, self.x_prev, self.x_prev2, tm, project=self.project)
            info.hessians += 1
        info.iterations = it
        dx_f = sv._newton_direction(x, self.x_prev, self.x_prev2, U, gf, tm, info)
        slope = _dot(gf, dx_f)
        if not slope < 0:  # not a descent direction: fall back to steepest descent
            dx_f = -gf / max(U.diagonal().max(), 1e-300)
            slope = _dot(gf, dx_f)
        dx = np.zeros(3 * sv.n)
        dx[sv.free_dofs] = dx_f
        self.fuse = sv.settings.fused_trial and it + 1 < sv._last_iterations  # the next iterate is not expected to converge
        self.fused_seconds = 0.0
        return dx.reshape(-1, 3), slope

    def trial(self, x, alpha, searching):
        sv = self.solver
        if self.fuse and searching and alpha == 1.0:
            t1 = time.perf_counter()
            e, grad, U = sv._evaluate_hessian(x, self.x_prev, self.x_prev2, self.project)
            self.fused_seconds = time.perf_counter() - t1
            self.info.hessians += 1
            return e, (grad, U)
        e, grad = sv._evaluate(x, self.x_prev, self.x_prev2)
        return e, (grad, None)

    def max_step(self, x, dx) -> float:
        """The step terms' :func:`~latentsim.solve.newton.max_step`: the step fraction that keeps every one
        finite (every vertex outside the colliders; 1 where no term limits it)."""
        return max_step(self.solver.step_terms, x, dx)

    def _time_line_search(self, seconds):
        self.info.timings["energy"] += seconds - self.fused_seconds
        self.info.timings["local"] += self.fused_seconds

    def accept(self, trial, e_old, seconds):
        self._time_line_search(seconds)
        self.grad, U = trial.payload
        self.U_next = U if trial.alpha == 1.0 and self.fuse else None

    def line_search_failed(self, it, seconds):
        self._time_line_search(seconds)
        gnorm = self.info.gradient_norm
        raise NewtonFailed(f"line search failed at iteration {it} (gradient norm {gnorm:.3e}, tolerance {self.tol:.3e})", gnorm, it)

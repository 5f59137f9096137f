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

The full-space gradient and Hessian come from :class:`latentsim.solve.implicit_euler.ImplicitEuler`
(the terms' ``local_gradient_hessian`` and the sparse assembly of
:mod:`latentsim.solve.sparse`); physics is not re-implemented here.

A subspace is any object with ``dim``, ``n_vertices``, ``hard_dirichlet``,
``dirichlet`` and ``jacobian(q, xD) -> (x (n, 3), J (3n, r))`` /
``map(q, xD) -> x``: :class:`LinearSubspace` (x = X + U q in the relative
coordinates) and :class:`DecoderSubspace` (the autoencoder's decoder).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from latentsim.physics.incremental_potential import IncrementalPotential, dirichlet_penalty
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings

__all__ = [
    "DecoderSubspace",
    "LinearSubspace",
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
# subspaces
# ---------------------------------------------------------------------------
def _relative_decode(coords, u: np.ndarray, xD: np.ndarray) -> np.ndarray:
    """Positions (n, 3) from an encoded vector u (d,) by the coordinates' own decode."""
    with torch.no_grad():
        return coords.decode(torch.from_numpy(np.asarray(u, dtype=np.float64)), torch.from_numpy(np.asarray(xD, dtype=np.float64))).numpy()


def _encoded_rows(coords) -> np.ndarray:
    """(d,) full-space DoF index of each entry of the encoded vector."""
    v = coords.encoded_vertices.numpy()
    return (3 * v[:, None] + np.arange(3)).reshape(-1)


class LinearSubspace:
    """x = decode_relative(u0 + U q, x*_D): a linear subspace of the relative coordinates.

    Parameters
    ----------
    coords : :class:`latentsim.latent.RelativeCoordinates` (``roots`` mode imposes
        the Dirichlet vertices exactly; ``mean`` mode leaves them to the penalty).
    u0 : (d,) offset in the encoded coordinates (e.g. the mean training frame).
    basis : (d, r) columns spanning the subspace.
    """

    def __init__(self, coords, u0, basis):
        self.coords = coords
        self.u0 = np.asarray(u0, dtype=np.float64).reshape(-1)
        self.basis = np.asarray(basis, dtype=np.float64)
        if self.basis.shape[0] != coords.dim or self.u0.shape[0] != coords.dim:
            raise ValueError(f"basis {self.basis.shape} / offset {self.u0.shape} do not match the coordinates' dimension {coords.dim}")
        self.dim = int(self.basis.shape[1])
        self.n_vertices = int(coords.n)
        self.hard_dirichlet = bool(coords.hard_dirichlet)
        self.dirichlet = coords.dirichlet.numpy()
        self._J = np.zeros((3 * self.n_vertices, self.dim))
        self._J[_encoded_rows(coords)] = self.basis

    @classmethod
    def from_frames(cls, coords, positions, dirichlet_positions, r: int):
        """PCA subspace of r components of frames (T, n, 3) with prescribed (T, m, 3)."""
        from latentsim.latent import pca_basis

        U = coords.encode(torch.as_tensor(positions, dtype=torch.float64), torch.as_tensor(dirichlet_positions, dtype=torch.float64))
        mean, V, _ = pca_basis(U.reshape(-1, coords.dim), r)
        return cls(coords, mean.numpy(), V.numpy().T)

    @classmethod
    def from_vectors(cls, coords, rest_positions, dirichlet, vectors):
        """Subspace about the rest state spanned by full-space vectors (3n, r), e.g. vibration
        modes (their rows on vertices the coordinates do not encode are dropped)."""
        X = np.asarray(rest_positions, dtype=np.float64)
        u0 = coords.encode(torch.as_tensor(X), torch.as_tensor(X[np.asarray(dirichlet, dtype=np.int64)])).numpy().reshape(-1)
        return cls(coords, u0, np.asarray(vectors, dtype=np.float64)[_encoded_rows(coords)])

    def map(self, q, xD) -> np.ndarray:
        return _relative_decode(self.coords, self.u0 + self.basis @ np.asarray(q, dtype=np.float64), xD)

    def jacobian(self, q, xD):
        return self.map(q, xD), self._J

    def project(self, x, xD) -> np.ndarray:
        """Least-squares reduced coordinates of positions x (n, 3)."""
        u = self.coords.encode(torch.as_tensor(x, dtype=torch.float64), torch.as_tensor(xD, dtype=torch.float64)).numpy()
        return np.linalg.lstsq(self.basis, u - self.u0, rcond=None)[0]


class DecoderSubspace:
    """x = decode_relative(Decoder(q), x*_D): the autoencoder's latent space (Fulton et al. 2019).

    The decoder is folded into float64 NumPy layers (:func:`latentsim.runtime.fold_decoder`)
    so that the map is smooth to round-off for the line search, and J comes
    from forward mode with all r tangents at once.
    """

    def __init__(self, ae, coords):
        from latentsim.runtime import NumpyStepper, fold_decoder

        self.ae, self.coords = ae, coords
        self.net = NumpyStepper(fold_decoder(ae, coords), dtype=np.float64)
        self._rows = _encoded_rows(coords)
        self.dim = int(ae.latent_dim)
        self.n_vertices = int(coords.n)
        self.hard_dirichlet = bool(coords.hard_dirichlet)
        self.dirichlet = coords.dirichlet.numpy()

    def map(self, q, xD) -> np.ndarray:
        return self.net.decode_from_u(self.net.decode_network(np.asarray(q, dtype=np.float64)), xD)

    def jacobian(self, q, xD):
        return self.net.decode_jacobian(np.asarray(q, dtype=np.float64), xD)

    def curvature(self, q, xD, grad) -> np.ndarray:
        """sum_i g_i d^2 x_i / dq dq (r, r) for a full-space gradient g (3n,): the term
        Gauss-Newton drops.  The relative-coordinates decode is affine in the encoded
        vector, so only the decoder's second derivatives enter."""
        return self.net.decode_curvature(np.asarray(q, dtype=np.float64), np.asarray(grad)[self._rows])

    def project(self, x, xD) -> np.ndarray:
        """The encoder's latent of positions x (n, 3)."""
        from latentsim.latent import encode_positions

        z = encode_positions(self.ae, self.coords, torch.as_tensor(x, dtype=torch.float64), torch.as_tensor(xD, dtype=torch.float64))
        return z.double().numpy()


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
    subspace : :class:`LinearSubspace`, :class:`DecoderSubspace` or any object
        with the same attributes and ``jacobian``/``map``.
    potential : the scene's IncrementalPotential with *every* elastic stencil
        (``build_potential(..., free_only=False)``, as ``potential_from_artefact``
        gives) when the subspace moves Dirichlet vertices (``mean`` coordinates).
    settings : :class:`ReducedSettings`.
    solver_options : keyword arguments for the internal
        :class:`latentsim.solve.implicit_euler.ImplicitEuler` that evaluates gradients and
        Hessians (e.g. its kernel choice).
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

    def _line_search(self, q, dq, e, slope, x_prev, x_prev2, xD, info):
        s = self.settings
        resolvable = -slope > s.energy_resolution * max(abs(e), 1e-300)
        alpha = 1.0
        while True:
            q_try = q + alpha * dq
            x_try = self.subspace.map(q_try, xD)
            e_try = self.energy(x_try, x_prev, x_prev2, xD)
            if not resolvable or (np.isfinite(e_try) and e_try <= e + s.armijo * alpha * slope):
                return q_try, x_try, e_try
            alpha *= 0.5
            if alpha < s.min_step:
                raise ReducedFailed(f"line search failed at iteration {info.iterations}", info)

    # -- one time step -----------------------------------------------------------
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
        when the test is not met in ``max_iterations`` or a value is non-finite.
        """
        xD = np.asarray(xD, dtype=np.float64)
        q_prev, q_prev2 = np.asarray(q_prev, dtype=np.float64), np.asarray(q_prev2, dtype=np.float64)
        candidates = [q_init] if q_init is not None else [2.0 * q_prev - q_prev2, q_prev]
        best = None
        for c in candidates:
            c = np.asarray(c, dtype=np.float64)
            x = self.subspace.map(c, xD)
            e = self.energy(x, x_prev, x_prev2, xD)
            if best is None or e < best[2]:
                best = (c, x, e)
        q, x, e = best
        info = ReducedStepInfo(energies=[e])
        self._tm = info.timings
        if self.settings.method == "lbfgs":
            return self._lbfgs(q, x, e, x_prev, x_prev2, xD, info)
        return self._newton(q, x, e, x_prev, x_prev2, xD, info)

    def _newton(self, q, x, e, x_prev, x_prev2, xD, info):
        s = self.settings
        tol = s.tolerance * self.f_ref
        for it in range(s.max_iterations + 1):
            info.iterations = it
            t0 = time.perf_counter()
            x, J = self.subspace.jacobian(q, xD)
            t1 = time.perf_counter()
            info.timings["map"] += t1 - t0
            d0 = info.timings["derivatives"]
            grad, gq, Hq = self._reduced_system(x, J, x_prev, x_prev2, xD, project=s.hessian == "projected")
            if self._converged(J, grad, tol, info):
                return q, x, info
            if it == s.max_iterations:
                break
            L = None
            if s.map_curvature and hasattr(self.subspace, "curvature"):
                # the full gradient does not vanish at a reduced minimum, so the map's
                # curvature matters: without it Gauss-Newton converges only linearly
                try:
                    L = np.linalg.cholesky(Hq + self.subspace.curvature(q, xD, grad))
                except np.linalg.LinAlgError:
                    info.gauss_newton += 1
            try:
                L = L if L is not None else np.linalg.cholesky(Hq)
            except np.linalg.LinAlgError:
                if s.hessian == "projected":
                    raise ReducedFailed("the reduced projected Hessian is not positive definite", info) from None
                info.projected += 1
                _, gq, Hq = self._reduced_system(x, J, x_prev, x_prev2, xD, project=True)
                L = np.linalg.cholesky(Hq + 1e-12 * np.trace(Hq) / len(Hq) * np.eye(len(Hq)))
            dq = -np.linalg.solve(L.T, np.linalg.solve(L, gq))
            slope = float(gq @ dq)
            t2 = time.perf_counter()
            info.timings["reduce"] += t2 - t1 - (info.timings["derivatives"] - d0)
            q, x, e = self._line_search(q, dq, e, slope, x_prev, x_prev2, xD, info)
            info.timings["line_search"] += time.perf_counter() - t2
            info.energies.append(e)
        raise ReducedFailed(f"no convergence in {s.max_iterations} iterations (tangent gradient {info.gradient_norm:.3e}, tolerance {tol:.3e})", info)

    def _lbfgs(self, q, x, e, x_prev, x_prev2, xD, info):
        """L-BFGS (two-loop recursion) with the reduced mass matrix J^T M J / h^2 as initial Hessian."""
        s = self.settings
        tol = s.tolerance * self.f_ref
        h2 = self.potential.dt ** 2
        m3 = np.repeat(self.inner.masses, 3)
        hist: list = []
        g_old = q_old = None
        H0 = None
        for it in range(s.max_iterations + 1):
            info.iterations = it
            x, J = self.subspace.jacobian(q, xD)
            grad = self.energy_gradient(x, x_prev, x_prev2, xD)[1]
            gq = J.T @ grad
            if self._converged(J, grad, tol, info):
                return q, x, info
            if it == s.max_iterations:
                break
            if H0 is None:
                M0 = (J * (m3 / h2)[:, None]).T @ J
                if self.penalty and len(self.D):
                    JD = J[self._Ddofs]
                    M0 += 2.0 * self.w_bc * (JD.T @ JD)
                H0 = np.linalg.cholesky(M0 + 1e-12 * np.trace(M0) / len(M0) * np.eye(len(M0)))
            if g_old is not None:
                sv, yv = q - q_old, gq - g_old
                if sv @ yv > 1e-12 * np.linalg.norm(sv) * np.linalg.norm(yv):
                    hist.append((sv, yv, 1.0 / (sv @ yv)))
                    hist = hist[-s.lbfgs_memory:]
            d = gq.copy()
            alphas = []
            for sv, yv, rho in reversed(hist):
                a = rho * (sv @ d)
                alphas.append(a)
                d -= a * yv
            d = np.linalg.solve(H0.T, np.linalg.solve(H0, d))
            for (sv, yv, rho), a in zip(hist, reversed(alphas)):
                d += sv * (a - rho * (yv @ d))
            dq = -d
            slope = float(gq @ dq)
            if not slope < 0:
                hist.clear()
                dq = -np.linalg.solve(H0.T, np.linalg.solve(H0, gq))
                slope = float(gq @ dq)
            q_old, g_old = q, gq
            q, x, e = self._line_search(q, dq, e, slope, x_prev, x_prev2, xD, info)
            info.energies.append(e)
        raise ReducedFailed(f"L-BFGS: no convergence in {s.max_iterations} iterations (tangent gradient {info.gradient_norm:.3e}, tolerance {tol:.3e})", info)


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

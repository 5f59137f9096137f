"""A contact projection of a latent rollout's frames (``rollout.contact_projection``; in neither paper).

The integrator's loss holds a contact barrier, but where a network does not learn a collider its rollout can pass
through it (the cloth over the ball, docs/measurements.md#contact).  The projection keeps what a user sees outside: each
decoded frame x_p within the scene's d_hat of a collider is replaced by the decode of the latent

    q* = argmin_q  1/(2 h^2) sum_i m_i |D(q)_i - x_p,i|^2 + B(D(q)),

the state of the autoencoder's latent space nearest x_p in the kinetic (mass-weighted) norm of one step, with B the
scene's barrier at the settings' reach and stiffness (by default the loss's: ten times d_hat, a hundredth of kappa),
continued quadratically below a fraction of that reach (finite inside a collider,
:meth:`~latentsim.physics.contact.ContactBarrier.extended`), and stiffened tenfold while the result is still inside.
Newton over q (r unknowns: the Hessian J^T H J plus the decoder's curvature, the Gauss-Newton matrix where that
is not positive definite) runs the one minimiser of :mod:`latentsim.solve.newton`, from q = z_t.

By default the projection changes the frames written, not the integrator's state: z_t goes on to the next step
as the network predicted it, so the rollout's dynamics does not respond to the collider; its frames are kept out
of it.  With ``feedback`` (:meth:`ContactProjection.step`) the projected latent is the state the next step starts
from: the projection is part of the integrator's step, as a collision response, and what the next step sees
(its two input latents, hence their velocity) has met the collider.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse
import torch

from latentsim.solve.newton import LineSearch, minimise

__all__ = ["ContactProjection", "FedBack"]


class _Stalled(Exception):
    """The line search found no decrease: the last iterate stands."""


class _Problem:
    """One frame's projection as the problem of :func:`latentsim.solve.newton.minimise` over q."""

    def __init__(self, owner: "ContactProjection", barrier, x_pred, xD):
        self.o, self.barrier, self.x_pred, self.xD = owner, barrier, x_pred, xD

    def energy(self, x) -> float:
        kinetic = 0.5 * float((self.o.weights * ((x - self.x_pred) ** 2).sum(-1)).sum())
        return kinetic + sum(float(t.energy(torch.as_tensor(x))) for t in self.barrier.terms())

    def stop(self, q, k) -> bool:
        o = self.o
        x, J = o.subspace.jacobian(q, self.xD)
        g = o.weights[:, None] * (x - self.x_pred)
        Hq = (J * o.dof_weights[:, None]).T @ J  # the mass term's J^T M J / h^2
        near = (self.barrier.distances(torch.as_tensor(x)) < self.barrier.d_hat).numpy()
        if near.any():  # the barrier's: its few vertices' 3 x 3 blocks
            gb, Hb = self.barrier.local_gradient_hessian(torch.as_tensor(x[near])[:, None, :], project=True)
            g[near] += gb.numpy()
            Jn = J.reshape(-1, 3, J.shape[-1])[near]
            Hq += (Jn.transpose(0, 2, 1) @ Hb.numpy() @ Jn).sum(0)
        for term in self.barrier.terms()[1:]:  # the surface's primitives within reach: their 3k x 3k blocks
            if getattr(term, "dynamic", False):  # self-contact: its gradient and its sparse Hessian over every DoF
                _, gs, U = term.energy_gradient_hessian(x, project=True)
                g += gs.reshape(-1, 3)
                Hq += J.T @ ((U + scipy.sparse.triu(U, 1).T) @ J)
                continue
            st = term.stencils.numpy()
            gs, Hs = term.local_gradient_hessian(term.gather(torch.as_tensor(x)), project=True)
            on = np.flatnonzero(gs.abs().amax(-1).numpy() > 0)
            if len(on):
                np.add.at(g, st[on], gs.numpy()[on].reshape(len(on), -1, 3))
                Js = J.reshape(-1, 3, J.shape[-1])[st[on]].reshape(len(on), -1, J.shape[-1])  # (P, 3k, r)
                Hq += (Js.transpose(0, 2, 1) @ Hs.numpy()[on] @ Js).sum(0)
        self.g, self.gq, self.Hq = g, J.T @ g.reshape(-1), Hq
        self.q, self.k = q, k
        return False

    def direction(self, q, k):
        curvature = getattr(self.o.subspace, "curvature", None)  # a linear map has none
        try:
            L = np.linalg.cholesky(self.Hq + curvature(q, self.xD, self.g.reshape(-1)))
        except (np.linalg.LinAlgError, TypeError):  # no curvature, or away from a minimum not PD: Gauss-Newton
            L = np.linalg.cholesky(self.Hq + 1e-12 * np.trace(self.Hq) / len(self.Hq) * np.eye(len(self.Hq)))
        dq = -np.linalg.solve(L.T, np.linalg.solve(L, self.gq))
        slope = float(self.gq @ dq)
        if -slope <= self.o.tolerance * max(self.e, 1e-300):  # the decrease left is below the tolerance: converged
            return None
        return dq, slope

    def trial(self, q, alpha, searching):
        x = self.o.subspace.map(q, self.xD)
        return self.energy(x), x

    def accept(self, trial, e_old, seconds):
        self.e = trial.energy

    def line_search_failed(self, k, seconds):
        raise _Stalled()


class ContactProjection:
    """Projects decoded frames out of a scene's colliders (the module docstring).

    Parameters
    ----------
    subspace : the autoencoder's latent space as a map with ``map``, ``jacobian`` and optionally ``curvature``
        (:class:`latentsim.latent.subspaces.DecoderSubspace`; any map of :mod:`latentsim.solve.reduced`).
    contact : the scene's :class:`~latentsim.physics.contact.ContactBarrier`; masses (n,), dt : the scene's.
    settings : the ``rollout.contact_projection`` block (every key): the barrier's ``barrier_d_hat``,
        ``barrier_kappa`` (multiples of the scene's) and ``barrier_extend_below``; ``iterations``, Newton's at most
        per attempt; ``tolerance``, the relative predicted decrease -g . dq / E below which an attempt has
        converged; ``stiffening``, the attempts after the first, each with kappa ten times larger, while the
        projected frame is still inside a collider (a softer barrier converges faster, but where the mass term
        outweighs it, stops inside).
    """

    def __init__(self, subspace, contact, masses, dt: float, settings: dict):
        self.subspace, self.contact = subspace, contact
        self.barrier = contact.extended(settings["barrier_extend_below"], settings["barrier_d_hat"], settings["barrier_kappa"])
        self.weights = np.asarray(masses, dtype=np.float64).reshape(-1) / float(dt) ** 2
        self.dof_weights = np.repeat(self.weights, 3)  # per coordinate, the rows of J
        self.iterations, self.tolerance = int(settings["iterations"]), float(settings["tolerance"])
        self.stiffening = int(settings["stiffening"])
        self.feedback = bool(settings["feedback"])
        self.search = LineSearch()

    def near(self, X, XD) -> np.ndarray:
        """(T,) bool: which frames X (T, n, 3) come within the scene's d_hat of a collider posed at their prescribed
        XD (T, m, 3) (where the full space's barrier acts; the projection's own reaches further, and would push
        frames that are fine away from the surface); a frame that is not finite is not.  One batched test."""
        X = torch.as_tensor(np.asarray(X, dtype=np.float64))
        finite = torch.isfinite(X).all(-1).all(-1)
        d = self.contact.clearance(torch.where(finite[:, None, None], X, 0.0), torch.as_tensor(np.asarray(XD, dtype=np.float64)))
        return (finite & (d < self.contact.d_hat)).numpy()

    def needed(self, x, xD) -> bool:
        """Whether one frame x (n, 3), prescribed at xD (m, 3), comes within the scene's d_hat of a collider (:meth:`near`)."""
        return bool(self.near(np.asarray(x)[None], np.asarray(xD)[None])[0])

    def project(self, z, x, xD):
        """(q*, D(q*), Newton iterations) of one frame: its latent z (r,), decode x (n, 3), prescribed xD (m, 3).
        Attempts with a stiffer barrier from where the last stopped, while D(q*) is inside a collider."""
        x, xD = np.asarray(x, dtype=np.float64), np.asarray(xD, dtype=np.float64)
        q, total = np.asarray(z, dtype=np.float64), 0
        surface = self.contact.posed(xD)
        for level in range(self.stiffening + 1):
            barrier = self.barrier if level == 0 else self.barrier.extended(self.barrier.extend_below / self.barrier.d_hat, 1.0, 10.0**level)
            problem = _Problem(self, barrier.posed(xD), x, xD)
            problem.e = problem.energy(self.subspace.map(q, xD))
            try:
                q, info = minimise(problem, q, problem.e, self.search, self.iterations)
                total += info.iterations
            except _Stalled:
                q, total = problem.q, total + problem.k
            y = self.subspace.map(q, xD)
            if float(surface.clearance(torch.as_tensor(y))) >= 0:
                break
        return q, y, total

    def frames(self, latents, positions, dirichlet_positions, last: int | None = None) -> dict:
        """Every frame of a rollout (latents (T, r), positions (T, n, 3), prescribed (T, m, 3)) up to ``last``
        (its last finite frame; all by default) that comes within the scene's d_hat of a collider, projected.

        Returns ``positions`` (a projected copy), ``projected`` (T,) bool, ``iterations`` (T,) (0 where not
        projected) and ``seconds`` (the projections' wall time, the tests of every frame included)."""
        X = np.array(positions, dtype=np.float64)
        T = len(X) if last is None else int(last) + 1
        projected = np.zeros(len(X), dtype=bool)
        iterations = np.zeros(len(X), dtype=np.int64)
        t0 = time.perf_counter()
        for t in np.flatnonzero(self.near(X[:T], np.asarray(dirichlet_positions)[:T])):
            _, X[t], iterations[t] = self.project(latents[t], X[t], dirichlet_positions[t])
            projected[t] = True
        return {"positions": X, "projected": projected, "iterations": iterations, "seconds": time.perf_counter() - t0}

    def correct(self, z: torch.Tensor, xD):
        """One predicted latent z (r,) at prescribed positions xD (m, 3) as the state to go on from:
        (z', projected, Newton iterations, depth of D(z) inside a collider [m]); z' = q* (z's dtype and
        device) where D(z) comes within the scene's d_hat of a collider, else z itself."""
        q, xD = z.detach().cpu().double().numpy(), np.asarray(xD, dtype=np.float64)
        x = self.subspace.map(q, xD)
        if not np.isfinite(x).all():
            return z, False, 0, 0.0
        d = float(self.contact.clearance(torch.as_tensor(x)[None], torch.as_tensor(xD)[None]).min())
        if d >= self.contact.d_hat:
            return z, False, 0, 0.0
        q, _, iterations = self.project(q, x, xD)
        return torch.as_tensor(q, dtype=z.dtype, device=z.device), True, iterations, max(-d, 0.0)

    def step(self, dirichlet_positions) -> "FedBack":
        """The projection as part of each step of a rollout prescribed at ``dirichlet_positions`` (T, m, 3)
        (``feedback``): a callable ``(t, z_t) -> z_t'`` for :func:`latentsim.latent.rollout.rollout`."""
        return FedBack(self, dirichlet_positions)


class FedBack:
    """The projection fed back (``feedback``): each latent the integrator predicts whose decode comes within the
    scene's d_hat of a collider is replaced by its projection q* before the next step, so the rollout's state, and
    with it the velocity the next step sees, responds to the collider.  Records per frame ``projected``,
    ``iterations`` and ``own_depth``, the depth of the network's prediction inside a collider before projection
    [m], and the wall ``seconds`` of the tests and projections."""

    def __init__(self, owner: ContactProjection, dirichlet_positions):
        self.o, self.XD = owner, np.asarray(dirichlet_positions, dtype=np.float64)
        T = len(self.XD)
        self.projected = np.zeros(T, dtype=bool)
        self.iterations = np.zeros(T, dtype=np.int64)
        self.own_depth = np.zeros(T)
        self.seconds = 0.0

    def __call__(self, t: int, z: torch.Tensor) -> torch.Tensor:
        t0 = time.perf_counter()
        z, self.projected[t], self.iterations[t], self.own_depth[t] = self.o.correct(z, self.XD[t])
        self.seconds += time.perf_counter() - t0
        return z

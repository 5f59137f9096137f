r"""Subspace dynamics in Neural Modes (Wang et al. 2024, Eq. 15) through ``latentsim.reduced``.

Eq. 15 minimises the incremental potential over the modal coordinates,

    z_{n+1} = argmin_z 1/(2h^2) ||n(z) - 2 x_n + x_{n-1}||_M^2 + E(n(z)),

which is :class:`latentsim.reduced.ReducedImplicitEuler` with the map
``x = phi(z, x*_D)`` given here (the paper solves it with L-BFGS; the reduced
solver also offers Gauss-Newton on J^T H J, the "exact reduced Hessian" the
paper lists as future work).  Our wang2024 scenes hold a Dirichlet set that
moves rigidly (hooves, base); the modes were computed with that set fixed at
rest, so the map carries the whole Neural Mode with the set's rigid motion,

    phi(z, x*_D) = R (n(z) - c_0) + c,     (R, c) the Kabsch fit of X_D -> x*_D,

which places the Dirichlet vertices exactly (n(z) leaves them at rest), so the
subspace imposes the boundary conditions (``hard_dirichlet``).  The map is
evaluated in float64 NumPy with its Jacobian by forward mode through the
GELU MLP (no autograd in the step).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import erf

from .neural_modes import NeuralModes

__all__ = ["NeuralModesSubspace"]


def _gelu(s):
    return 0.5 * s * (1.0 + erf(s / math.sqrt(2.0)))


def _gelu_prime(s):
    return 0.5 * (1.0 + erf(s / math.sqrt(2.0))) + s * np.exp(-0.5 * s * s) / math.sqrt(2.0 * math.pi)


class NeuralModesSubspace:
    """x = R (n(z) - c_0) + c for :class:`latentsim.reduced.ReducedImplicitEuler`.

    Parameters
    ----------
    model : trained :class:`NeuralModes` (its fixed DoFs are the scene's Dirichlet set).
    dirichlet : (m,) the scene's Dirichlet vertices.
    linear_only : use the linear modes alone (y = 0): the linear-modes baseline.
    """

    def __init__(self, model: NeuralModes, dirichlet, linear_only: bool = False):
        self.dim = int(model.m)
        self.n_vertices = int(model.n)
        self.dirichlet = np.asarray(dirichlet, dtype=np.int64)
        self.hard_dirichlet = len(self.dirichlet) > 0
        self.X = model.X.detach().numpy().copy()
        self.E = model.E.detach().numpy().copy()
        self.linear_only = bool(linear_only)
        lin = [m for m in model.mlp if hasattr(m, "weight")]
        self.layers = [(m.weight.detach().numpy().copy(), m.bias.detach().numpy().copy()) for m in lin]
        self.mask = model.mask.detach().numpy().copy()
        self.R = None if model.R is None else model.R.detach().numpy().copy()
        self.MR = None if model.MR is None else model.MR.detach().numpy().copy()
        self.y0 = self._mlp(np.zeros(self.dim))[0] if model.exact_origin else np.zeros_like(self.X)
        XD = self.X.reshape(-1, 3)[self.dirichlet]
        self.c0 = XD.mean(0) if len(XD) else np.zeros(3)
        self._XDc = XD - self.c0

    def _mlp(self, q, jac=False):
        a, J = q, (np.eye(self.dim) if jac else None)
        for W, b in self.layers[:-1]:
            s = W @ a + b
            a = _gelu(s)
            if jac:
                J = _gelu_prime(s)[:, None] * (W @ J)
        W, b = self.layers[-1]
        return W @ a + b, (W @ J if jac else None)

    def _correction(self, q, jac):
        if self.linear_only:
            return np.zeros_like(self.X), (np.zeros((len(self.X), self.dim)) if jac else None)
        y, Jy = self._mlp(q, jac)
        y = (y - self.y0) * self.mask
        if jac:
            Jy = Jy * self.mask[:, None]
        if self.R is not None:
            y = y - self.R @ (self.MR.T @ y)
            if jac:
                Jy = Jy - self.R @ (self.MR.T @ Jy)
        return y, Jy

    def _frame(self, xD):
        """Rotation R and centre c of the best rigid fit of the rest Dirichlet set onto xD."""
        if not len(self.dirichlet):
            return np.eye(3), self.c0
        xD = np.asarray(xD, dtype=np.float64)
        c = xD.mean(0)
        U, _, Vt = np.linalg.svd(self._XDc.T @ (xD - c))
        d = np.sign(np.linalg.det(U @ Vt))
        return (U @ np.diag([1.0, 1.0, d]) @ Vt).T, c

    def map(self, q, xD) -> np.ndarray:
        q = np.asarray(q, dtype=np.float64)
        y, _ = self._correction(q, False)
        n = (self.X + self.E @ q + y).reshape(-1, 3)
        R, c = self._frame(xD)
        return (n - self.c0) @ R.T + c

    def jacobian(self, q, xD):
        q = np.asarray(q, dtype=np.float64)
        y, Jy = self._correction(q, True)
        n = (self.X + self.E @ q + y).reshape(-1, 3)
        R, c = self._frame(xD)
        Jn = (self.E + Jy).reshape(-1, 3, self.dim)
        J = np.einsum("ij,njr->nir", R, Jn).reshape(-1, self.dim)
        return (n - self.c0) @ R.T + c, J

    def project(self, x, xD) -> np.ndarray:
        """Modal coordinates of positions x (n,3): least squares on the linear part (l^T y = 0)."""
        R, c = self._frame(xD)
        u = ((np.asarray(x) - c) @ R + self.c0).reshape(-1) - self.X
        return np.linalg.lstsq(self.E, u, rcond=None)[0]

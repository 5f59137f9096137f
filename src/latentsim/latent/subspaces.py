"""Subspaces of the reduced solvers: maps x = phi(q, x*_D) from r reduced coordinates to positions.

A subspace (Fulton et al. 2019, Sec. 3; with a linear map, classical subspace dynamics) maps
reduced coordinates q (r,) and the prescribed Dirichlet positions x*_D (m, 3) to the n vertex
positions through the autoencoder's relative coordinates (:class:`latentsim.latent.RelativeCoordinates`):

- :class:`LinearSubspace`: x = decode_relative(u0 + U q, x*_D), e.g. PCA of training frames or
  vibration modes; J = d phi / d q is constant.
- :class:`DecoderSubspace`: x = decode_relative(Decoder(q), x*_D), the autoencoder's latent space,
  with J by forward mode and the decoder's curvature sum_i g_i d^2 x_i / dq^2.

Each has ``dim``, ``n_vertices``, ``hard_dirichlet``, ``dirichlet``, ``map(q, xD) -> x (n, 3)``,
``jacobian(q, xD) -> (x, J (3n, r))`` and ``project(x, xD) -> q``, the interface of
:class:`latentsim.solve.reduced.ReducedImplicitEuler`.
"""

from __future__ import annotations

import numpy as np
import torch

from latentsim.latent import encode_positions, pca_basis
from latentsim.runtime import NumpyStepper, fold_decoder
from latentsim.runtime.frame import frame_pose

__all__ = ["DecoderSubspace", "LinearSubspace"]


def _relative_decode(coords, u: np.ndarray, xD: np.ndarray) -> np.ndarray:
    """Positions (n, 3) from an encoded vector u (d,) by the coordinates' own decode."""
    with torch.no_grad():
        return coords.decode(torch.from_numpy(np.asarray(u, dtype=np.float64)), torch.from_numpy(np.asarray(xD, dtype=np.float64))).numpy()


def _frame(coords, xD):
    """(R (3, 3), c (1, 3)) of coordinates with a rigid frame at prescribed positions xD (m, 3); None without one."""
    if not getattr(coords, "rigid", False):
        return None
    return frame_pose(np.asarray(xD, dtype=np.float64), coords.frame_vertices, coords.rest_frame.numpy())


def _turned(J: np.ndarray, R) -> np.ndarray:
    """Rows (3n, ...) of per-vertex 3-vectors in the frame carried out of it (R applied to each vertex's rows)."""
    if R is None:
        return J
    return np.einsum("ij,nj...->ni...", R, J.reshape((-1, 3) + J.shape[1:])).reshape(J.shape)


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

    linear = True  # phi(q + dq) - phi(q) = J dq: a reduced step's chord is its path

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
        pose = _frame(self.coords, xD)
        return self.map(q, xD), self._J if pose is None else _turned(self._J, pose[0])

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
        self.ae, self.coords = ae, coords
        self.net = NumpyStepper(fold_decoder(ae, coords), dtype=np.float64)
        self._rows = _encoded_rows(coords)
        self.dim = int(ae.latent_dim)
        self.n_vertices = int(coords.n)
        self.hard_dirichlet = bool(coords.hard_dirichlet)
        self.dirichlet = coords.dirichlet.numpy()

    def _local(self, xD):
        """xD carried into the coordinates' rigid frame, and (R, c); xD itself and None without one."""
        pose = _frame(self.coords, xD)
        return (xD, None) if pose is None else ((np.asarray(xD, dtype=np.float64) - pose[1]) @ pose[0], pose)

    def map(self, q, xD) -> np.ndarray:
        xl, pose = self._local(xD)
        x = self.net.decode_from_u(self.net.decode_network(np.asarray(q, dtype=np.float64)), xl)
        return x if pose is None else x @ pose[0].T + pose[1]

    def jacobian(self, q, xD):
        xl, pose = self._local(xD)
        x, J = self.net.decode_jacobian(np.asarray(q, dtype=np.float64), xl)
        return (x, J) if pose is None else (x @ pose[0].T + pose[1], _turned(J, pose[0]))

    def curvature(self, q, xD, grad) -> np.ndarray:
        """sum_i g_i d^2 x_i / dq dq (r, r) for a full-space gradient g (3n,): the term
        Gauss-Newton drops.  The relative-coordinates decode is affine in the encoded
        vector, so only the decoder's second derivatives enter."""
        pose = _frame(self.coords, xD)
        grad = np.asarray(grad, dtype=np.float64)
        if pose is not None:  # the gradient as the frame sees it, R^T g per vertex
            grad = (grad.reshape(-1, 3) @ pose[0]).reshape(-1)
        return self.net.decode_curvature(np.asarray(q, dtype=np.float64), grad[self._rows])

    def project(self, x, xD) -> np.ndarray:
        """The encoder's latent of positions x (n, 3)."""
        z = encode_positions(self.ae, self.coords, torch.as_tensor(x, dtype=torch.float64), torch.as_tensor(xD, dtype=torch.float64))
        return z.double().numpy()

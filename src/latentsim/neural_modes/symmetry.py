r"""Latent-space structure of a learned subspace (Wang et al. 2024, Fig. 3): a half-turn symmetry, latent walks.

A scene whose mesh, fixed DoFs and modes map onto themselves under the half turn T about its axis of
least extent (each mode onto plus or minus itself, S = diag(parity)) has an energy and a ground truth
(Eq. 9) with n(S z) = T n(z); :func:`symmetry_error` measures how far a map is from it, and
``network.NeuralModes`` can build it in (``symmetry='half_turn'``).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["half_turn", "latent_walk", "symmetry_error", "turn"]


def half_turn(X, cells, modes, fixed_dofs=None, tol: float = 1e-9):
    """The half turn about the axis of least extent through the centroid, where it is a symmetry.

    It must map the vertices (to ``tol`` times the bounding-box diagonal), the cells (K,k) and the fixed
    DoFs onto themselves, and each mode onto plus or minus itself (a non-degenerate mode's parity).
    Returns ``(perm, R, parity)`` -- vertex i turns into vertex perm[i], R the (3,3) rotation, parity
    (m,) the modes' signs -- or None when any of that fails.
    """
    X = np.asarray(X, dtype=np.float64)
    c = X.mean(0)
    normal = np.linalg.svd(X - c, full_matrices=False)[2][-1]
    R = 2.0 * np.outer(normal, normal) - np.eye(3)
    dist, perm = cKDTree(X).query((X - c) @ R.T + c)
    if dist.max() > tol * np.linalg.norm(np.ptp(X, axis=0)) or len(np.unique(perm)) != len(X):
        return None
    if {tuple(sorted(e)) for e in np.asarray(cells)} != {tuple(sorted(e)) for e in perm[np.asarray(cells)]}:
        return None
    fixed = np.unique(np.asarray(fixed_dofs if fixed_dofs is not None else [], dtype=np.int64) // 3)
    if not np.array_equal(np.sort(perm[fixed]), fixed):
        return None
    E = np.asarray(modes, dtype=np.float64).T.reshape(-1, len(X), 3)
    turned = turn(E, perm, R)
    parity = np.sign(np.einsum("kij,kij->k", turned, E))
    if np.any(np.linalg.norm((turned - parity[:, None, None] * E).reshape(len(E), -1), axis=1) > 1e-6 * np.linalg.norm(E.reshape(len(E), -1), axis=1)):
        return None  # a degenerate pair: the turn mixes modes
    return perm, R, parity


def turn(u, perm, R) -> np.ndarray:
    """A displacement field u (..., n, 3) carried by the symmetry: out[..., perm[i]] = R u[..., i]."""
    u = np.asarray(u)
    out = np.empty_like(u)
    out[..., perm, :] = u @ R.T
    return out


def symmetry_error(x, z, X, symmetry) -> tuple[float, float]:
    """(mean, max) over samples z != 0 of |turn(u(z)) - u(S z)| / |u(z)|, u = x - X, S = diag(parity).

    A map that keeps the symmetry of the energy, the modes and the mesh (as Eq. 9 does) gives 0.
    ``z`` (N,m) must hold S z with every z; NaNs when ``symmetry`` is None.
    """
    if symmetry is None:
        return float("nan"), float("nan")
    perm, R, parity = symmetry
    z = np.asarray(z, dtype=np.float64)
    u = np.asarray(x, dtype=np.float64) - np.asarray(X, dtype=np.float64)
    dist, j = cKDTree(z).query(z * parity)
    if dist.max() > 1e-9 * max(np.abs(z).max(), 1e-300):
        raise ValueError("symmetry_error: the sample set does not hold the mirrored coordinates S z of every z")
    size = np.linalg.norm(u.reshape(len(u), -1), axis=1)
    keep = np.any(z != 0, axis=1) & (size > 0)  # z = 0 maps to the rest state (the origin error's business)
    err = np.linalg.norm((turn(u, perm, R) - u[j]).reshape(len(u), -1), axis=1)[keep] / size[keep]
    return float(err.mean()), float(err.max())


def latent_walk(decode, low, high, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Shapes along each latent coordinate i from low[i] to high[i], the others at 0.

    ``decode`` maps (k, m) coordinates to positions (k, n, 3).  Returns coordinates (m, steps) and
    positions (m, steps, n, 3).
    """
    low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    m = len(low)
    coords = np.linspace(low, high, steps).T
    pos = []
    for i in range(m):
        z = np.zeros((steps, m))
        z[:, i] = coords[i]
        pos.append(decode(z))
    return coords, np.stack(pos)

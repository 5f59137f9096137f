r"""Latent directions at the origin and their correlation (mode collapse, Wang et al. 2024, Fig. 4).

The columns of the Jacobian dx/dz at z = 0 are a subspace's latent directions; their normalised
mass-weighted Gram matrix is the identity for M-orthogonal directions (Neural Modes: the linear
modes) and has eigenvalues near zero where directions collapse onto each other.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["direction_correlation", "latent_directions"]


def latent_directions(decoder, m: int) -> torch.Tensor:
    """Jacobian (3n, m) of z -> x (flattened) at z = 0; ``decoder`` maps (1, m) -> (1, n, 3)."""
    z0 = torch.zeros(1, m, dtype=torch.float64)
    J = torch.autograd.functional.jacobian(lambda z: decoder(z).reshape(-1), z0)
    return J.reshape(-1, m).detach()


def direction_correlation(J, masses) -> tuple[np.ndarray, np.ndarray]:
    """Normalised mass-weighted Gram matrix C_ij = <J_i, J_j>_M / (|J_i|_M |J_j|_M) and its eigenvalues (descending)."""
    J = np.asarray(J, dtype=np.float64)
    m3 = np.repeat(np.asarray(masses, dtype=np.float64), 3)
    G = J.T @ (m3[:, None] * J)
    d = np.sqrt(np.clip(np.diag(G), 1e-300, None))
    C = G / np.outer(d, d)
    return C, np.sort(np.linalg.eigvalsh(C))[::-1]

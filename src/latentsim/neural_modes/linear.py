r"""Linear modes of a scene (Wang et al. 2024, Sec. 3.2): the lowest vibration modes, rigid modes, fixed DoFs.

The lowest eigenpairs of the rest-state elastic Hessian generalised with the lumped mass matrix,

    K e_i = omega_i^2 M e_i,

found by shift-invert Lanczos (``solve.implicit_euler.lowest_modes``: ``eigsh``, never a dense
matrix).  With Dirichlet constraints the prescribed DoFs are removed.  A free-floating object has
six zero modes (rigid translations and rotations); K is singular there, so the shift is a small
*negative* sigma (K - sigma M is positive definite), the k + 6 lowest pairs are computed, and the
six whose span is the rigid space (checked against the explicit rigid basis R) are dropped; the kept
modes are projected M-orthogonally off span(R).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from latentsim.physics.incremental_potential import IncrementalPotential
from latentsim.solve.modes import fix_sign, lowest_modes

__all__ = ["LinearModes", "fixed_dofs", "linear_modes", "rigid_modes"]


@dataclass
class LinearModes:
    """Lowest vibration modes of a scene.

    Attributes
    ----------
    omega2 : (k,) eigenvalues omega^2 [1/s^2], ascending.
    modes : (3n, k) modes over all DoFs (zero on prescribed DoFs), normalised
        as ``normalization`` says: 'mass' (e^T M e = 1) or 'euclidean' (|e| = 1).
    free_dofs : (f,) the DoFs the eigenproblem ran on.
    rigid_removed : 6 for a free-floating object, else 0.
    normalization : 'mass' | 'euclidean'.
    """

    omega2: np.ndarray
    modes: np.ndarray
    free_dofs: np.ndarray
    rigid_removed: int
    normalization: str


def rigid_modes(X, masses) -> np.ndarray:
    """M-orthonormal basis (3n, 6) of rigid motions of rest positions X (n,3): 3 translations, 3 rotations."""
    X = np.asarray(X, dtype=np.float64)
    m3 = np.repeat(np.asarray(masses, dtype=np.float64), 3)
    c = np.average(X, axis=0, weights=np.asarray(masses, dtype=np.float64))
    r = X - c
    n = len(X)
    R = np.zeros((3 * n, 6))
    for a in range(3):
        R[a::3, a] = 1.0
        w = np.zeros(3)
        w[a] = 1.0
        R[:, 3 + a] = np.cross(w, r).reshape(-1)
    # M-orthonormalise (Gram-Schmidt in the M inner product, via Cholesky of the Gram matrix)
    G = R.T @ (m3[:, None] * R)
    Lc = np.linalg.cholesky(G)
    return np.linalg.solve(Lc, R.T).T


def fixed_dofs(dirichlet, boundary: str) -> np.ndarray:
    """The DoFs the modes and the correction leave at rest: every DoF of the ``dirichlet`` vertices with
    ``boundary='dirichlet'``, none with 'free'."""
    if boundary == "free":
        return np.zeros(0, dtype=np.int64)
    D = np.asarray(dirichlet, dtype=np.int64)
    return (3 * D[:, None] + np.arange(3)).reshape(-1)


def linear_modes(
    potential: IncrementalPotential, k: int, x, boundary: str = "dirichlet", normalization: str = "mass", tol: float = 0.0
) -> LinearModes:
    """The k lowest non-rigid modes of K e = omega^2 M e at ``x``.

    Parameters
    ----------
    potential : the scene's potential (its elastic terms and lumped masses; its
        ``dirichlet`` set is removed when ``boundary='dirichlet'``).
    k : number of modes.
    x : (n,3) state at which K is evaluated, normally the rest state (only
        there is K positive semi-definite, which the shift-invert needs).
    boundary : 'dirichlet' (remove the prescribed DoFs) or 'free' (all DoFs
        free; the six rigid modes are removed).
    normalization : 'mass' (e^T M e = 1) or 'euclidean' (|e|_2 = 1, the
        scaling of the paper's released sheet modes, whose modal box is
        [-0.625, 0.625]^m).
    """
    if boundary not in ("dirichlet", "free"):
        raise ValueError(f"boundary '{boundary}': use 'dirichlet' or 'free'")
    if normalization not in ("mass", "euclidean"):
        raise ValueError(f"normalization '{normalization}': use 'mass' or 'euclidean'")
    n = potential.n_vertices
    masses = potential.masses.detach().cpu().numpy().astype(np.float64)
    x = np.asarray(x, dtype=np.float64)
    free = np.ones(n, dtype=bool)
    if boundary == "dirichlet":
        free[potential.dirichlet.cpu().numpy()] = False
    free_dofs = np.flatnonzero(np.repeat(free, 3))
    n_rigid = 6 if boundary == "free" else 0
    m = np.repeat(masses, 3)[free_dofs]
    w, V, _ = lowest_modes(potential, k + n_rigid, x, free_dofs, tol=tol)
    if n_rigid:
        R = rigid_modes(x, masses)
        # the six lowest must span the rigid space: their M-projection onto it keeps them whole
        low = V[:, :n_rigid]
        captured = np.linalg.norm(R.T @ (m[:, None] * low), axis=0)
        if not np.all(captured > 1 - 1e-6):
            raise RuntimeError(f"the six lowest modes are not rigid (captured {captured}); is the object connected?")
        w, V = w[n_rigid:], V[:, n_rigid:]
        V = V - R @ (R.T @ (m[:, None] * V))  # deflate the rigid space exactly
        V = V / np.sqrt((m[:, None] * V * V).sum(0))
    if normalization == "euclidean":
        V = V / np.linalg.norm(V, axis=0)
    V = fix_sign(V)
    full = np.zeros((3 * n, k))
    full[free_dofs] = V
    return LinearModes(omega2=w, modes=full, free_dofs=free_dofs, rigid_removed=n_rigid, normalization=normalization)

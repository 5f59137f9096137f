"""Linear vibration modes: the stiffness matrix and the lowest generalised eigenpairs.

At a state x (normally the rest state) the elastic Hessian K = d^2 E / dx^2 over the free DoFs
and the lumped mass M give the modes K v = omega^2 M v (the linear modes of Neural Modes, Wang
et al. 2024, Sec. 3; the vibration-mode subspace of the reduced baselines), found by sparse
shift-invert Lanczos with a fixed start vector and a fixed sign per mode.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from latentsim.physics.incremental_potential import IncrementalPotential
from latentsim.solve.assembly import CompiledAssembly
from latentsim.solve.sparse import HessianPattern, symmetric_from_upper

__all__ = ["fix_sign", "lowest_modes", "stiffness_matrix"]


def stiffness_matrix(potential: IncrementalPotential, x, free_dofs=None):
    """Elastic Hessian K (full symmetric CSR over ``free_dofs``) at state x (n,3).

    Uses each term's projected per-stencil Hessian (the compiled assembly); at the rest state
    the elastic Hessian is positive semi-definite, so the projection leaves it unchanged there
    (the use this serves: linear modes and frequencies).

    Returns
    -------
    K : (f, f) CSR, free_dofs : (f,)
    """
    n = potential.n_vertices
    if free_dofs is None:
        free = np.ones(n, dtype=bool)
        free[potential.dirichlet.cpu().numpy()] = False
        free_dofs = np.flatnonzero(np.repeat(free, 3))
    pattern = HessianPattern(n, [t.stencils.cpu().numpy() for t in potential.terms], free_dofs)
    assembly = CompiledAssembly.of(potential.terms, pattern, n)
    _, U = assembly.gradient_hessian(np.ascontiguousarray(x, dtype=np.float64).reshape(n, 3), np.zeros(3 * n), project=True)
    return symmetric_from_upper(U).tocsr(), free_dofs


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
    K, free = stiffness_matrix(potential, x, free_dofs)
    m = np.repeat(potential.masses.detach().cpu().numpy().astype(np.float64), 3)[free]
    if k >= len(free) - 1:
        raise ValueError(f"{k} modes asked of a {len(free)}-DoF system")
    sigma = -1e-8 * abs(K.diagonal()).max() / m.max()
    v0 = np.random.default_rng(0).standard_normal(len(free))
    w, V = scipy.sparse.linalg.eigsh(K.tocsc(), k=k, M=scipy.sparse.diags(m).tocsc(), sigma=sigma, which="LM", tol=tol, v0=v0)
    order = np.argsort(w)
    return w[order], fix_sign(V[:, order]), free


def fix_sign(V: np.ndarray, ties: float = 1e-8) -> np.ndarray:
    """Make each column's largest-magnitude entry positive (eigenvectors have no sign).

    Entries within a relative ``ties`` of the column's largest magnitude count as tied, and the
    first of them decides: a mode with a symmetry has pairs of entries of equal size (and opposite
    sign under a half turn), where a plain argmax would let the last bit of rounding pick the sign.
    """
    mag = np.abs(V)
    idx = np.argmax(mag >= (1.0 - ties) * mag.max(axis=0), axis=0)  # the first of the tied entries
    s = np.sign(V[idx, np.arange(V.shape[1])])
    s[s == 0] = 1.0
    return V * s

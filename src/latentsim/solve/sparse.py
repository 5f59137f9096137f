"""Sparse assembly of per-stencil Hessians and the linear solvers Newton uses.

Assembly: the sparsity pattern of the free-DoF Hessian is computed once per
scene from the terms' stencils; each Newton iteration then scatters the
per-stencil blocks into the CSR data array with a single ``np.bincount`` over
precomputed slot indices (no COO->CSR conversion in the hot path).

Linear solvers (all for symmetric positive definite systems, which the
PSD-projected Hessian plus M/h^2 is):

- ``banded``  : ``scipy.linalg.solveh_banded`` (Cholesky of a banded matrix).
  Rods stored rod by rod give a bandwidth of 8 DoFs; milliseconds for 10k DoF.
- ``pardiso`` : MKL PARDISO through ``pypardiso`` (symbolic analysis reused
  across iterations by pypardiso when the pattern is unchanged).
- ``splu``    : SciPy SuperLU, always available, slowest.
- ``auto``    : banded when the bandwidth is small, else pardiso if it imports,
  else splu.

``LinearSolver.solve_indefinite`` solves a symmetric system that need not be definite (the exact
Hessian of the Neural Modes ground truth): PARDISO's symmetric indefinite factorisation with
its symbolic analysis reused, else SuperLU.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg


class HessianPattern:
    """CSR pattern of the upper triangle of the Hessian restricted to free DoFs.

    Parameters
    ----------
    n_vertices : int
    stencil_sets : list of (E_i, k_i) int arrays, one per energy term
    free_dofs : (f,) int array of free DoF indices (3*vertex + axis), sorted

    After construction, ``assemble(blocks, diagonal)`` builds the matrix from
    per-stencil blocks (E_i, 3k_i, 3k_i) and a per-DoF diagonal (3n,).
    """

    def __init__(self, n_vertices, stencil_sets, free_dofs):
        self.n_dofs = 3 * n_vertices
        self.free_dofs = np.asarray(free_dofs, dtype=np.int64)
        local = -np.ones(self.n_dofs, dtype=np.int64)
        local[self.free_dofs] = np.arange(len(self.free_dofs))
        self.local = local
        f = len(self.free_dofs)
        rows, cols, self._keep = [], [], []
        for st in stencil_sets:
            st = np.asarray(st, dtype=np.int64)
            dofs = (3 * st[:, :, None] + np.arange(3)).reshape(len(st), 3 * st.shape[1])  # (E, 3k)
            ld = local[dofs]
            r = np.broadcast_to(ld[:, :, None], ld.shape + (ld.shape[1],)).reshape(-1)
            c = np.broadcast_to(ld[:, None, :], ld.shape[:1] + (ld.shape[1],) * 2).reshape(-1)
            keep = (r >= 0) & (c >= r)  # free DoFs, upper triangle only
            self._keep.append(keep)
            rows.append(r[keep])
            cols.append(c[keep])
        diag = np.arange(f)
        rows.append(diag)
        cols.append(diag)
        rows = np.concatenate(rows)
        cols = np.concatenate(cols)
        key = rows * f + cols
        uniq, slot = np.unique(key, return_inverse=True)
        self._keys = uniq
        self.nnz = len(uniq)
        self.indices = (uniq % f).astype(np.int32)
        row_of = uniq // f
        self.indptr = np.zeros(f + 1, dtype=np.int32)
        np.cumsum(np.bincount(row_of, minlength=f), out=self.indptr[1:])
        # split slot back into per-term pieces and the diagonal
        self._slots = []
        start = 0
        for keep in self._keep:
            n = int(keep.sum())
            self._slots.append(slot[start : start + n])
            start += n
        self._diag_slot = slot[start:]
        self.all_slots = slot
        self.shape = (f, f)
        self.bandwidth = int(np.max(np.abs(row_of - self.indices))) if self.nnz else 0

    def stencil_slots(self, stencils) -> np.ndarray:
        """Where each stencil Hessian entry goes in the CSR data array.

        Parameters
        ----------
        stencils : (E, k) int vertex indices (one of the sets of the constructor).

        Returns
        -------
        (E, 3k (3k+1) / 2) int32: for the upper-triangle entries (p, q), p <= q,
        of the (3k, 3k) stencil Hessian in row-major order, the data index of
        the matrix entry (min(r, c), max(r, c)) of the free DoFs r, c of p and
        q, or -1 where p or q is a Dirichlet DoF.  Adding H[p, q] there for
        every stencil gives the same matrix as ``assemble`` (H symmetric).
        """
        st = np.asarray(stencils, dtype=np.int64)
        k3 = 3 * st.shape[1]
        ld = self.local[(3 * st[:, :, None] + np.arange(3)).reshape(len(st), k3)]
        iu, ju = np.triu_indices(k3)
        r, c = ld[:, iu], ld[:, ju]
        valid = (r >= 0) & (c >= 0)
        key = np.minimum(r, c) * self.shape[0] + np.maximum(r, c)
        pos = np.searchsorted(self._keys, np.where(valid, key, 0))
        if not np.all(self._keys[np.minimum(pos, self.nnz - 1)][valid] == key[valid]):
            raise ValueError("stencils are not part of this Hessian pattern")
        return np.where(valid, pos, -1).astype(np.int32)

    def band_positions(self) -> np.ndarray:
        """(nnz,) flat indices of each CSR entry in the upper banded storage ab (bandwidth + 1, f)
        held column by column (Fortran order, LAPACK's): entry (i, j) at j (bandwidth + 1) + bandwidth + i - j.

        Column order keeps the entries of one stencil within a few cache lines.
        """
        rows = np.repeat(np.arange(self.shape[0]), np.diff(self.indptr))
        return self.indices * (self.bandwidth + 1) + self.bandwidth + rows - self.indices

    @property
    def diagonal_slots(self) -> np.ndarray:
        """(f,) data indices of the diagonal entries of the free DoFs."""
        return self._diag_slot

    def assemble(self, blocks, diagonal):
        """Upper-triangular CSR matrix from per-term blocks (E_i, 3k_i, 3k_i) and a (3n,) diagonal."""
        weights = [np.asarray(b).reshape(-1)[keep] for b, keep in zip(blocks, self._keep)]
        weights.append(np.asarray(diagonal)[self.free_dofs])
        data = np.bincount(self.all_slots, weights=np.concatenate(weights), minlength=self.nnz)
        return scipy.sparse.csr_matrix((data, self.indices, self.indptr), shape=self.shape)


def scatter_gradient(n_vertices, stencil_sets, grads):
    """Sum per-stencil gradients (E_i, 3k_i) into a (3n,) vector."""
    out = np.zeros(3 * n_vertices)
    for st, g in zip(stencil_sets, grads):
        st = np.asarray(st, dtype=np.int64)
        dofs = (3 * st[:, :, None] + np.arange(3)).reshape(-1)
        out += np.bincount(dofs, weights=np.asarray(g).reshape(-1), minlength=3 * n_vertices)
    return out


class NotPositiveDefinite(ArithmeticError):
    """The factorisation met a non-positive pivot: the matrix is not SPD."""


def _to_banded_upper(U: scipy.sparse.csr_matrix, bw: int) -> np.ndarray:
    """Upper banded storage ab[bw + i - j, j] = U[i, j] of an upper-triangular CSR."""
    n = U.shape[0]
    rows = np.repeat(np.arange(n), np.diff(U.indptr))
    ab = np.zeros((bw + 1, n), order="F")
    ab[bw + rows - U.indices, U.indices] = U.data
    return ab


class BandedUpper:
    """A symmetric matrix in LAPACK's upper banded storage, ab[bw + i - j, j] = A[i, j] (i <= j).

    What the full-space solver assembles into when its linear solver is
    'banded' (rods): the kernels add straight into ``ab`` at slots from
    ``HessianPattern.band_positions``, so no CSR -> band conversion runs.
    """

    def __init__(self, data: np.ndarray, pattern: HessianPattern):
        """data : ((bandwidth + 1) f,) the storage column by column (``band_positions``)."""
        self.data = data
        self.pattern = pattern
        self.shape = pattern.shape

    @property
    def ab(self) -> np.ndarray:
        """(bandwidth + 1, f) Fortran-ordered view of the storage, ab[bw + i - j, j] = A[i, j]."""
        return self.data.reshape(self.shape[0], self.pattern.bandwidth + 1).T

    @classmethod
    def from_csr(cls, U, pattern: HessianPattern) -> BandedUpper:
        """The banded storage of an upper-triangular CSR matrix of ``pattern``."""
        data = np.zeros((pattern.bandwidth + 1) * pattern.shape[0])
        data[pattern.band_positions()] = U.data
        return cls(data, pattern)

    def diagonal(self) -> np.ndarray:
        return self.ab[-1]

    def tocsr(self) -> scipy.sparse.csr_matrix:
        """The upper-triangular CSR matrix of the pattern."""
        p = self.pattern
        data = self.data[p.band_positions()]
        return scipy.sparse.csr_matrix((data, p.indices, p.indptr), shape=p.shape)


def symmetric_from_upper(U):
    """Full symmetric matrix from its upper triangle."""
    return U + scipy.sparse.triu(U, k=1).T


class LinearSolver:
    """Solve A x = b for the SPD Newton systems of one scene.

    ``method`` is one of 'auto', 'banded', 'pardiso', 'splu'.  'auto' resolves
    once, from the pattern's bandwidth, to the fastest method available.  ``dynamic``: the matrices
    hold entries beyond ``pattern`` that change between solves (self-contact's pairs): never banded,
    and PARDISO's symbolic analysis is redone whenever the matrix's pattern is not the last one's.
    """

    BANDED_MAX = 64

    def __init__(self, pattern: HessianPattern, method: str = "auto", dynamic: bool = False):
        if method not in ("auto", "banded", "pardiso", "splu"):
            raise ValueError(f"linear solver '{method}': use one of auto, banded, pardiso, splu")
        if dynamic and method == "banded":
            raise ValueError("linear solver 'banded': a matrix whose pattern changes (self-contact) needs pardiso or splu")
        self.dynamic = bool(dynamic)
        self._analysed: dict = {}  # matrix type -> the (indptr, indices) PARDISO analysed (dynamic only)
        if method == "auto":
            if pattern.bandwidth <= self.BANDED_MAX and not dynamic:
                method = "banded"
            else:
                method = "pardiso" if _pardiso_available() else "splu"
        self.method = method
        self.bandwidth = pattern.bandwidth
        # the PARDISO solvers by matrix type, each with its symbolic analysis done
        self._pardiso_by_type: dict = {}
        # symbolic analyses and numeric factorisations of ``solve_indefinite``, by method
        self.indefinite_counts = {"analyses": 0, "pardiso": 0, "splu": 0}

    def solve(self, U, b):
        """Solve with the upper-triangular CSR ``U`` of an SPD matrix (or its ``BandedUpper``)."""
        if isinstance(U, BandedUpper) and self.method != "banded":
            U = U.tocsr()
        if self.method == "banded":
            ab = U.ab if isinstance(U, BandedUpper) else _to_banded_upper(U, self.bandwidth)
            try:
                return scipy.linalg.solveh_banded(ab, b, lower=False, check_finite=False)
            except np.linalg.LinAlgError as e:
                raise NotPositiveDefinite(str(e)) from e
        if self.method == "pardiso":
            return self._solve_pardiso(U, b)
        return scipy.sparse.linalg.splu(symmetric_from_upper(U).tocsc()).solve(b)

    def _pardiso(self, mtype: int, U, b):
        # PARDISO of matrix type ``mtype`` (2: real SPD, -2: real symmetric indefinite) on the upper
        # triangle.  The pattern never changes within a scene (unless ``dynamic``), so the symbolic analysis
        # (phase 11, fill-in reducing ordering) runs once per type; each call only refactors numerically and
        # solves (phase 23).  Raises pypardiso's PyPardisoError.
        import pypardiso  # here, not at the top: an optional dependency that loads MKL (heavy)

        b = np.asfortranarray(b, dtype=np.float64)
        p = self._pardiso_by_type.get(mtype)
        analyse = p is None
        if p is None:
            p = pypardiso.PyPardisoSolver(mtype=mtype)
            p.msglvl = 0
            self._pardiso_by_type[mtype] = p
        if self.dynamic:
            last = self._analysed.get(mtype)
            analyse = last is None or not (np.array_equal(last[0], U.indptr) and np.array_equal(last[1], U.indices))
        if analyse:
            p._check_A(U)
            p.set_phase(11)
            p._call_pardiso(U, b)
            if self.dynamic:
                self._analysed[mtype] = (U.indptr.copy(), U.indices.copy())
            if mtype == -2:
                self.indefinite_counts["analyses"] += 1
        p.set_phase(23)
        return p._call_pardiso(U, b)

    def _solve_pardiso(self, U, b):
        import pypardiso

        try:
            return self._pardiso(2, U, b)
        except pypardiso.pardiso_wrapper.PyPardisoError as e:
            if e.value == -4:  # zero pivot: not positive definite
                raise NotPositiveDefinite(f"PARDISO: {e}") from e
            raise

    # residual ||A x - b|| / ||b|| above which an indefinite PARDISO solve (whose pivots may have been
    # perturbed) is redone by SuperLU
    INDEFINITE_RTOL = 1e-8

    def solve_indefinite(self, U, b):
        """Solve with the upper-triangular CSR ``U`` of a symmetric matrix that need not be definite
        (where ``solve`` raised :class:`NotPositiveDefinite`): the same solution as SuperLU on the full
        matrix, by PARDISO's symmetric indefinite factorisation (mtype -2, Bunch-Kaufman pivoting)
        with its symbolic analysis reused across calls when the method is 'pardiso', and SuperLU when
        PARDISO is not the method or its solution's residual exceeds ``INDEFINITE_RTOL``."""
        if isinstance(U, BandedUpper):
            U = U.tocsr()
        if self.method == "pardiso":
            x = self._solve_pardiso_indefinite(U, b)
            if x is not None:
                r = symmetric_from_upper(U) @ x.reshape(b.shape) - b
                if np.linalg.norm(r) <= self.INDEFINITE_RTOL * max(float(np.linalg.norm(b)), 1e-300):
                    return x
        self.indefinite_counts["splu"] += 1
        return scipy.sparse.linalg.splu(symmetric_from_upper(U).tocsc()).solve(b)

    def _solve_pardiso_indefinite(self, U, b):
        """PARDISO's symmetric indefinite solve, or None where it fails."""
        import pypardiso

        self.indefinite_counts["pardiso"] += 1
        try:
            return self._pardiso(-2, U, b)
        except pypardiso.pardiso_wrapper.PyPardisoError:
            return None


def _pardiso_available() -> bool:
    try:
        import pypardiso  # noqa: F401  (optional, loads MKL: imported only to ask)
    except Exception:  # pragma: no cover - depends on the install
        return False
    return True

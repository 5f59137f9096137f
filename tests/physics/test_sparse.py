"""Assembly into the precomputed CSR pattern, and the linear solvers, against dense references."""

import numpy as np
import pytest
import scipy.sparse

from latentsim.solve.sparse import HessianPattern, LinearSolver, scatter_gradient, symmetric_from_upper


def random_blocks(rng, stencils):
    k3 = 3 * stencils.shape[1]
    A = rng.standard_normal((len(stencils), k3, k3))
    return A @ A.transpose(0, 2, 1)  # SPD blocks


def dense_assembly(n, stencils, blocks, diag, free):
    K = np.diag(diag.copy())
    for st, B in zip(stencils, blocks):
        for e, b in zip(st, B):
            dofs = (3 * e[:, None] + np.arange(3)).reshape(-1)
            K[np.ix_(dofs, dofs)] += b
    return K[np.ix_(free, free)]


@pytest.fixture
def system():
    rng = np.random.default_rng(0)
    n = 30
    tris = np.array([[i, i + 1, i + 2] for i in range(n - 2)])
    edges = np.array([[i, (i + 7) % n] for i in range(n)])
    free = np.setdiff1d(np.arange(3 * n), [0, 1, 2, 9, 10, 11])
    blocks = [random_blocks(rng, tris), random_blocks(rng, edges)]
    diag = rng.uniform(1, 2, 3 * n)
    return n, [tris, edges], blocks, diag, free, rng


def test_assembly_matches_dense(system):
    n, stencils, blocks, diag, free, _ = system
    pattern = HessianPattern(n, stencils, free)
    U = pattern.assemble(blocks, diag)
    assert scipy.sparse.tril(U, k=-1).nnz == 0
    K = symmetric_from_upper(U).toarray()
    assert np.allclose(K, dense_assembly(n, stencils, blocks, diag, free))


def test_gradient_scatter(system):
    n, stencils, _, _, _, rng = system
    grads = [rng.standard_normal((len(s), 3 * s.shape[1])) for s in stencils]
    expected = np.zeros(3 * n)
    for st, g in zip(stencils, grads):
        np.add.at(expected, (3 * st[:, :, None] + np.arange(3)).reshape(len(st), -1), g)
    assert np.allclose(scatter_gradient(n, stencils, grads), expected)


@pytest.mark.parametrize("method", ["banded", "pardiso", "splu"])
def test_solvers_agree_with_dense(system, method):
    n, stencils, blocks, diag, free, rng = system
    pattern = HessianPattern(n, stencils, free)
    if method == "banded":  # a banded system: consecutive-vertex stencils only
        stencils = stencils[:1]
        blocks = blocks[:1]
        pattern = HessianPattern(n, stencils, free)
    U = pattern.assemble(blocks, diag)
    b = rng.standard_normal(len(free))
    solver = LinearSolver(pattern, method)
    x = solver.solve(U, b)
    K = dense_assembly(n, stencils, blocks, diag, free)
    assert np.allclose(K @ x, b, atol=1e-8)
    # the same solver object on new values (pardiso reuses its symbolic analysis)
    U2 = pattern.assemble([2 * B for B in blocks], diag)
    assert np.allclose(2 * (K - np.diag(diag[free])) @ solver.solve(U2, b) + diag[free] * solver.solve(U2, b), b, atol=1e-8)


def test_auto_picks_banded_for_small_bandwidth(system):
    n, stencils, _, _, free, _ = system
    assert LinearSolver(HessianPattern(n, stencils[:1], free)).method == "banded"
    assert LinearSolver(HessianPattern(n, stencils, free)).method in ("pardiso", "splu")


def test_unknown_solver_is_named(system):
    n, stencils, _, _, free, _ = system
    with pytest.raises(ValueError, match="'cholesky'"):
        LinearSolver(HessianPattern(n, stencils, free), "cholesky")


@pytest.mark.parametrize("method", ["pardiso", "splu"])
def test_indefinite_solves_agree_with_dense_and_pardiso_analyses_once(system, method):
    """``solve_indefinite`` on symmetric indefinite systems of one pattern: the dense solution; with
    PARDISO one symbolic analysis for every call and no SuperLU factorisation."""
    if method == "pardiso":
        pytest.importorskip("pypardiso")
    n, stencils, blocks, diag, free, rng = system
    pattern = HessianPattern(n, stencils, free)
    solver = LinearSolver(pattern, method)
    eig = np.linalg.eigvalsh(dense_assembly(n, stencils, blocks, diag, free))
    for q in (0.2, 0.5, 0.8):  # shifted into the spectrum: indefinite
        shift = -0.5 * (eig[int(q * len(eig))] + eig[int(q * len(eig)) + 1])
        U = pattern.assemble(blocks, diag + shift)
        K = dense_assembly(n, stencils, blocks, diag + shift, free)
        assert np.linalg.eigvalsh(K).min() < 0 < np.linalg.eigvalsh(K).max()
        b = rng.standard_normal((len(free), 2))
        x = solver.solve_indefinite(U, b)
        assert np.allclose(K @ x.reshape(b.shape), b, atol=1e-8 * np.abs(b).max())
    counts = solver.indefinite_counts
    if method == "pardiso":
        assert counts == {"analyses": 1, "pardiso": 3, "splu": 0}
    else:
        assert counts["splu"] == 3 and counts["pardiso"] == 0

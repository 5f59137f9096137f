"""Self-contact (``physics.self_contact``): its derivatives, its invariance, and a sheet dropped on another that
rests on it with no point of one within the thickness of the other (the IPC Toolkit's distances and
intersection test), where without the term it falls through."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
import torch

ipctk = pytest.importorskip("ipctk")

from latentsim.mesh import cloth_grid  # noqa: E402
from latentsim.physics.mesh_contact import unique_edges  # noqa: E402
from latentsim.physics import kept_pairs, self_contact  # noqa: E402
from latentsim.physics.self_contact import SelfContact  # noqa: E402
from latentsim.solve.sparse import LinearSolver  # noqa: E402

F64 = torch.float64


def two_sheets(offset, jitter=0.0, seed=0):
    """A 0.2 m sheet of 6 x 6 cells in the x-z plane and a 0.12 m one of 5 x 5 cells ``offset`` from it."""
    Xa, ta = cloth_grid(6, 6, 0.2, 0.2, plane="xz")
    Xb, tb = cloth_grid(5, 5, 0.12, 0.12, plane="xz")
    X = np.vstack([np.asarray(Xa, np.float64), np.asarray(Xb, np.float64) + offset])
    X += np.random.default_rng(seed).normal(scale=jitter, size=X.shape)
    return X, np.vstack([ta, np.asarray(tb) + len(Xa)]).astype(np.int64), len(Xa)


def full(U):
    return (U + scipy.sparse.triu(U, 1).T).toarray()


def test_derivatives_are_the_energys_and_the_pairs_are_the_toolkits():
    """Two crumpled sheets a barrier's reach apart: the gradient equals autograd's of the PyTorch energy, the exact Hessian
    the finite differences of the gradient, the projected one is PSD; every pair nearer than d_hat by the toolkit's
    own brute-force distances is one of the term's, at the same distance."""
    X, tris, na = two_sheets([0.013, 0.002, 0.007], jitter=3e-4)
    sc = SelfContact(len(X), tris, d_hat=0.004, kappa=10.0, thickness=0.0005)
    e, g, U = sc.energy_gradient_hessian(X, project=False)
    assert e > 0
    xt = torch.tensor(X, requires_grad=True)
    E = sc.energy(xt)
    (ga,) = torch.autograd.grad(E, xt)
    assert float(E.detach()) == pytest.approx(e, rel=1e-12)
    assert np.abs(g - ga.numpy().ravel()).max() <= 1e-10 * np.abs(g).max()
    H, eps = full(U), 1e-7
    for i in np.argsort(-np.abs(g))[:6]:
        xp, xm = X.ravel().copy(), X.ravel().copy()
        xp[i] += eps
        xm[i] -= eps
        fd = (sc.energy_gradient_hessian(xp.reshape(-1, 3), hessian=False)[1] - sc.energy_gradient_hessian(xm.reshape(-1, 3), hessian=False)[1]) / (2 * eps)
        assert np.abs(fd - H[:, i]).max() <= 1e-5 * np.abs(H[:, i]).max()
    assert np.linalg.eigvalsh(full(sc.energy_gradient_hessian(X, project=True)[2])).min() >= -1e-9 * np.abs(H).max()
    ids, d, n_fv = sc.pairs(X, sc.d_hat)
    assert _found(ids, n_fv) == _within_reach(X, tris, sc) and len(ids) > 20


def _within_reach(X, tris, sc):
    """The pairs within reach, by the toolkit's distances over every vertex-triangle and edge-edge pair sharing no vertex."""
    want = set()
    for v in range(len(X)):
        for t in tris:
            if v not in t and np.sqrt(ipctk.point_triangle_distance(X[v], *X[t])) - sc.thickness < sc.d_hat:
                want.add((v, *t))
    E2 = unique_edges(tris)
    for a in range(len(E2)):
        for b in range(a + 1, len(E2)):
            if not set(E2[a]) & set(E2[b]) and np.sqrt(ipctk.edge_edge_distance(*X[E2[a]], *X[E2[b]])) - sc.thickness < sc.d_hat:
                want.add(tuple(sorted([tuple(E2[a]), tuple(E2[b])])))
    return want


def _found(ids, n_fv):
    return {tuple(i) for i in ids[:n_fv]} | {tuple(sorted([tuple(i[:2]), tuple(i[2:])])) for i in ids[n_fv:]}


def test_pairs_of_a_kept_state_serve_the_states_near_it(monkeypatch):
    """The pairs found for a state are taken again for a state whose every vertex lies within the margin m of it, and are
    still every pair within reach there: sheets 6 mm apart, beyond the reach and the thickness r = 4.5 mm and beyond
    r + m, each moved 0.9 m towards the other, come within reach (found in the kept state at r + 2m); moved 1.1 m each,
    the pairs are found afresh.  With none kept, every state is searched."""
    X, tris, na = two_sheets([0.013, 0.006, 0.007], jitter=3e-4)
    sc = SelfContact(len(X), tris, d_hat=0.004, kappa=10.0, thickness=0.0005)
    m = (sc.d_hat + sc.thickness) / 4
    searches = []
    search = self_contact._candidates
    monkeypatch.setattr(self_contact, "_candidates", lambda *a: searches.append(1) or search(*a))
    first = sc.pairs(X, sc.d_hat)
    for step, kept in ((0.9 * m, 1), (1.1 * m, 2)):
        Y = X.copy()
        Y[:na, 1] += step
        Y[na:, 1] -= step
        ids, d, n_fv = sc.pairs(Y, sc.d_hat)
        assert _found(ids, n_fv) == _within_reach(Y, tris, sc)
        assert len(searches) == kept  # taken from X's, then found afresh
        assert len(ids) > len(first[0])
    monkeypatch.setattr(kept_pairs, "KEPT_STATES", 0)  # none kept: every state searched
    unkept = SelfContact(len(X), tris, d_hat=0.004, kappa=10.0, thickness=0.0005)
    assert [len(unkept.pairs(X, sc.d_hat)[0]) for _ in range(2)] == [len(first[0])] * 2 and len(searches) == 4


def test_compiled_selection_leaves_energy_gradient_and_distances_unchanged(monkeypatch):
    """The pairs within reach are selected by compiled distances (``kernels.distances.within``) before PyTorch
    measures them: every state's energy, its gradient and the least distance equal, to the bit, those with every
    candidate measured in PyTorch, over many states of sheets whose pairs straddle the reach."""
    X, tris, na = two_sheets([0.013, 0.004, 0.007], jitter=1e-3)
    rng = np.random.default_rng(3)
    states = np.stack([X + rng.normal(scale=5e-4, size=X.shape) for _ in range(12)])

    def measured():
        sc = SelfContact(len(X), tris, d_hat=0.004, kappa=10.0, thickness=0.0005, extend_below=0.0004)
        x = torch.tensor(states, requires_grad=True)
        e = sc.energy(x)
        (g,) = torch.autograd.grad(e.sum(), x)
        return e.detach(), g, sc.distances(x, sc.d_hat), [len(sc.pairs(s, sc.d_hat)[0]) for s in states]

    selected = measured()
    monkeypatch.setattr(self_contact, "within", lambda x, state, ids, n_fv, reach: np.ones(len(ids), bool))
    everything = measured()
    assert all(torch.equal(a, b) for a, b in zip(selected[:3], everything[:3])) and selected[3] == everything[3]
    assert (selected[0] > 0).sum() >= 10 and min(selected[3]) > 10


def test_energy_is_zero_apart_and_invariant_under_rigid_motion():
    X, tris, _ = two_sheets([0.013, 0.002, 0.007], jitter=3e-4)
    sc = SelfContact(len(X), tris, d_hat=0.004, kappa=10.0, thickness=0.0005)
    far, _, _ = two_sheets([0.013, 0.02, 0.007])
    assert float(sc.energy(torch.tensor(far))) == 0.0
    e = float(sc.energy(torch.tensor(X)))
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, c, s], [0, -s, c]])
    moved = X @ R.T + [0.3, -1.0, 2.0]
    assert float(sc.energy(torch.tensor(moved))) == pytest.approx(e, rel=1e-9)


def test_a_sheet_dropped_on_another_rests_on_it_and_falls_through_without_the_term():
    """The small sheet falls from 1 cm onto the large one, held at every vertex: every step converges with the term in the
    residual; by the toolkit no triangle crosses another and the sheets never come within the thickness; the small one
    ends resting in the barrier's reach.  Without the term the same drop passes through the large sheet."""
    from latentsim.scene import build_potential
    from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings

    def drop(self_contact: bool, steps: int):
        X, tris, na = two_sheets([0.013, 0.01, 0.007])
        arrays = {"rest_positions": X, "triangles": tris, "dirichlet": np.arange(na)}
        material = {"youngs_modulus": 1e4, "poisson_ratio": 0.3, "density": 200.0, "thickness": 0.002}
        pot = build_potential("shell", arrays, material, 1 / 30, [0, -9.81, 0], free_only=True, contact=None)
        if self_contact:
            pot.extra_terms = [SelfContact(len(X), tris, D_HAT, kappa=100.0 * float(pot.masses.max()) * 9.81 / D_HAT, thickness=THICK)]
        solver = ImplicitEuler(pot, NewtonSettings(tolerance=1e-6))
        x2 = x1 = X.copy()
        out = []
        for _ in range(steps):
            x, info = solver.step(x1, x2, X[:na])
            out.append((x, info))
            x2, x1 = x1, x
        return X, tris, na, solver, out

    D_HAT, THICK = 0.002, 0.001
    X, tris, na, solver, frames = drop(True, 12)
    assert solver.linear.method != "banded"
    cm = ipctk.CollisionMesh(np.asfortranarray(X), np.asfortranarray(unique_edges(tris).astype(np.int32)), np.asfortranarray(tris.astype(np.int32)))
    nearest = []
    for x, info in frames:
        assert info.gradient_norm <= 1e-6 * solver.f_ref
        V = np.asfortranarray(x)
        assert not ipctk.has_intersections(cm, V)
        col = ipctk.NormalCollisions()
        col.build(cm, V, 0.02)
        nearest.append(np.sqrt(col.compute_minimum_distance(cm, V)))
    assert min(nearest) > THICK
    assert nearest[-1] < THICK + D_HAT and frames[-1][0][na:, 1].min() > 0  # resting on the large sheet
    *_, free_fall = drop(False, 12)
    assert free_fall[-1][0][na:, 1].max() < -0.01


def test_pardiso_analyses_again_when_the_pattern_changes():
    """A dynamic solver solves systems of two patterns (a chain, then the chain with a long-range coupling) as SuperLU does."""
    pytest.importorskip("pypardiso")
    from latentsim.solve.sparse import HessianPattern

    n = 30
    chain = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
    pattern = HessianPattern(n, [chain], np.arange(3 * n))
    solver = LinearSolver(pattern, "pardiso", dynamic=True)
    rng = np.random.default_rng(1)
    A = scipy.sparse.diags([4.0] * (3 * n)) + scipy.sparse.diags([-1.0] * (3 * n - 3), 3)
    U = scipy.sparse.triu(A).tocsr()
    coupling = scipy.sparse.csr_matrix(([0.5], ([2], [80])), shape=U.shape)
    for M in (U, U + coupling, U):
        b = rng.normal(size=3 * n)
        x = solver.solve(M.tocsr(), b)
        S = (M + scipy.sparse.triu(M, 1).T).tocsc()
        np.testing.assert_allclose(S @ x, b, rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="banded"):
        LinearSolver(pattern, "banded", dynamic=True)

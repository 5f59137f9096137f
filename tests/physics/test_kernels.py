"""Compiled per-stencil kernels against the PyTorch energies and their autograd derivatives.

The kernels (``latentsim.physics.kernels``) compile the energies, gradients and
Hessians of the terms that ``rods``, ``shells`` and ``tets`` define once in
PyTorch; they must give the same numbers as the energies and as autograd (the
oracle, ``base.autograd_gradient_hessian``).  Each test would fail for a wrong
formula, a wrong index order, a wrong projection, a wrong scatter into the
sparse Hessian, or a result that depends on threads or on the machine's load.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from latentsim.physics import kernels
from latentsim.physics.base import autograd_gradient_hessian, project_psd, project_psd_translation_free
from latentsim.physics.kernels import core, dispatch
from latentsim.physics.rods import rod_topology
from latentsim.mesh import beam_tets, cloth_grid, rod_bundle
from latentsim.scene import build_potential
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings
from latentsim.solve.sparse import HessianPattern, scatter_gradient

MATERIAL = {"youngs_modulus": 1e5, "poisson_ratio": 0.35, "density": 1000.0, "radius": 1e-3, "thickness": 2e-3}


def scene(model, law="stvk"):
    """A small scene of each model with a few Dirichlet vertices (``law``: the material.model)."""
    if model == "tets":
        X, T = beam_tets(4, 2, 2, 0.4, 0.1, 0.1, tets_per_cell=6)
        arrays = {"rest_positions": X, "tets": T, "dirichlet": np.flatnonzero(X[:, 0] < 1e-9)}
    elif model == "rods":
        X, edges, roots = rod_bundle(3, 9, 0.2, 0.05)
        _, triples = rod_topology(3, 9)
        dirichlet = np.concatenate([roots, roots + 1])
        arrays = {"rest_positions": X, "edges": edges, "triples": triples.numpy(), "dirichlet": dirichlet}
    else:
        X, tris = cloth_grid(4, 4, 0.4, 0.4)
        arrays = {"rest_positions": X, "triangles": tris, "dirichlet": np.array([0, 4])}
    return build_potential(model, arrays, {**MATERIAL, "model": law}, 0.01, [0.0, -9.81, 0.0]), np.asarray(X)


def states(X, seed, count=3):
    """Random states around the rest shape, from mild to strongly distorted (some elements inverted)."""
    rng = np.random.default_rng(seed)
    size = np.ptp(X, axis=0).max()
    R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    out = []
    for s in np.linspace(0.02, 0.3, count):
        out.append(X @ R.T + rng.normal(size=3) + s * size / 4 * rng.normal(size=X.shape))
    return out


MODELS = ["tets", "rods", "shell"]


@pytest.fixture(scope="module", params=MODELS)
def case(request):
    pot, X = scene(request.param)
    return request.param, pot, X, [kernels.term_kernel(t) for t in pot.terms]


def close(a, b, rtol=1e-9):
    """|a - b| <= rtol * max|b| (entries of very different size share one scale)."""
    a, b = np.asarray(a), np.asarray(b)
    return np.abs(a - b).max() <= rtol * max(np.abs(b).max(), 1e-300)


def test_every_term_has_a_kernel(case):
    _, pot, _, ks = case
    assert all(k is not None for k in ks)
    assert [k.name for k in ks] == [t.name for t in pot.terms]


def test_energy_matches_torch(case):
    _, pot, X, ks = case
    for term, k in zip(pot.terms, ks):
        scale = 0.0
        for x in states(X, 1):
            ref = float(term.energy(torch.from_numpy(x)))
            assert abs(k.energy(x) - ref) <= 1e-11 * abs(ref), term.name
            scale = max(scale, abs(ref))
        assert abs(k.energy(X)) <= 1e-12 * scale, term.name  # zero at rest


def test_fused_energy_gradient_and_assembly_energy(case):
    """The one-pass energy + gradient (line search) gives the energy kernel's energy, and it and
    the assembly pass give the autograd gradient of the PyTorch energy."""
    _, pot, X, ks = case
    n = pot.n_vertices
    x = states(X, 5)[2]
    for term, k in zip(pot.terms, ks):
        st = term.stencils.numpy()
        xt = torch.from_numpy(x).requires_grad_(True)
        (g_ref,) = torch.autograd.grad(term.energy(xt), xt)
        g_ref = g_ref.numpy().reshape(-1)
        grad = np.zeros(3 * n)
        e = k.energy_gradient(x, grad)
        assert abs(e - k.energy(x)) <= 1e-12 * abs(e), term.name
        assert close(grad, g_ref, 1e-10), term.name
        free = np.arange(3 * n)
        pattern = HessianPattern(n, [st], free)
        for project in (False, True):  # the Hessian pass returns the same energy, to the bit
            grad2, data = np.zeros(3 * n), np.zeros(pattern.nnz)
            assert k.accumulate(x, grad2, data, pattern.stencil_slots(st), project) == e, term.name
            assert np.array_equal(grad2, grad), term.name


def test_exact_gradient_hessian_match_autograd(case):
    _, pot, X, ks = case
    for x in states(X, 2):
        xt = torch.from_numpy(x)
        for term, k in zip(pot.terms, ks):
            xe = term.gather(xt)
            g, H = k.local(x, project=False)
            g_ad, H_ad = autograd_gradient_hessian(term, xe, project=False)
            assert close(g, g_ad.numpy(), 1e-7), term.name
            assert close(H, H_ad.numpy(), 1e-7), term.name
            g_t, H_t = term.local_gradient_hessian(xe, project=False)  # the term's entry point: the same kernels
            assert np.array_equal(g_t.numpy(), g) and np.array_equal(H_t.numpy(), H), term.name


def test_projected_hessian_matches_autograd(case):
    """The eigenvalue clamp: PSD, equal to the exact Hessian where that one is PSD, and (rods,
    shells: the clamp of the stencil Hessian) the autograd oracle's ``project_psd``.  The tets'
    clamp of dP/dF in F-space has its own oracle (``test_energy_tets``)."""
    model, pot, X, ks = case
    for x in states(X, 3):
        xt = torch.from_numpy(x)
        for term, k in zip(pot.terms, ks):
            g, H = k.local(x, project=True)
            g_e, He = k.local(x, project=False)
            assert np.array_equal(g, g_e), term.name
            w = np.linalg.eigvalsh(H)
            assert w.min() >= -1e-10 * np.abs(w).max(), term.name
            psd = np.linalg.eigvalsh(He).min(axis=1) >= 0.0
            if psd.any():
                assert close(H[psd], He[psd], 1e-8), term.name
            if model != "tets":
                _, H_ad = autograd_gradient_hessian(term, term.gather(xt), project=True)
                assert close(H, H_ad.numpy(), 1e-8), term.name


def test_one_psd_projection():
    """``core.project_psd`` on the translation-free basis (the kernels' clamp) and on the identity,
    and PyTorch's ``project_psd_translation_free`` (a use of ``project_psd``), are one clamp."""
    rng = np.random.default_rng(0)
    for k in (2, 3, 4):
        B = core.translation_free_basis(k)
        n, m = B.shape
        assert np.allclose(B.T @ B, np.eye(m), atol=1e-14) and np.allclose(B.reshape(k, 3, m).sum(0), 0.0, atol=1e-14)
        A = rng.standard_normal((m, m))
        H = B @ (A + A.T) @ B.T  # translation invariant, indefinite
        ref = project_psd(torch.from_numpy(H)[None])[0].numpy()
        assert np.linalg.eigvalsh(H).min() < -1e-3 and np.linalg.eigvalsh(ref).min() > -1e-12
        for basis in (B, np.eye(n)):
            mm = basis.shape[1]
            out = H.copy()
            scratch = np.empty((mm, mm)), np.empty((n, mm)), np.empty((mm, mm)), np.empty(mm), np.empty((n, mm))
            core.project_psd(out, basis, *scratch, core.NO_FRAME, False)
            assert close(out, ref, 1e-12)
        assert close(project_psd_translation_free(torch.from_numpy(H)[None], k)[0].numpy(), ref, 1e-12)


@pytest.mark.parametrize("project", [False, True])
def test_scatter_into_csr_equals_assembly(case, project):
    """Kernels adding into the CSR data at precomputed slots give the matrix that ``assemble``
    builds from their per-stencil blocks."""
    _, pot, X, ks = case
    x = states(X, 4)[1]
    n = pot.n_vertices
    free = np.ones(n, dtype=bool)
    free[pot.dirichlet.numpy()] = False
    free_dofs = np.flatnonzero(np.repeat(free, 3))
    stencils = [t.stencils.numpy() for t in pot.terms]
    pattern = HessianPattern(n, stencils, free_dofs)
    pairs = [k.local(x, project) for k in ks]
    diag = np.linspace(1.0, 2.0, 3 * n)
    U_ref = pattern.assemble([H for _, H in pairs], diag).toarray()
    g_ref = scatter_gradient(n, stencils, [g for g, _ in pairs])
    grad, data = np.zeros(3 * n), np.zeros(pattern.nnz)
    for st, k in zip(stencils, ks):
        k.accumulate(x, grad, data, pattern.stencil_slots(st), project)
    data[pattern.diagonal_slots] += diag[free_dofs]
    U = np.zeros(pattern.shape)
    rows = np.repeat(np.arange(pattern.shape[0]), np.diff(pattern.indptr))
    U[rows, pattern.indices] = data
    assert close(U, U_ref, 1e-12)
    assert close(grad, g_ref, 1e-12)


@pytest.mark.parametrize("model", MODELS)
def test_solver_steps_reach_the_incremental_potentials_stationary_point(model):
    """Each Newton step (compiled kernels) ends where the PyTorch incremental potential's autograd
    gradient over the free DoFs meets the solver's tolerance, with the Dirichlet vertices at
    their targets."""
    pot, X = scene(model)
    solver = ImplicitEuler(pot, NewtonSettings(tolerance=1e-9))
    D = solver.dirichlet
    x2 = x1 = X.copy()
    for t in range(1, 4):
        target = X[D] + np.array([0.02 * t, 0.0, 0.01 * t])
        x, info = solver.step(x1, x2, target)
        assert info.iterations >= 1
        assert np.array_equal(x[D], target)
        xt = torch.from_numpy(x.copy()).requires_grad_(True)
        (g,) = torch.autograd.grad(pot(xt, torch.from_numpy(x1), torch.from_numpy(x2), penalty=False), xt)
        assert np.linalg.norm(g.numpy().reshape(-1)[solver.free_dofs]) <= 1.01e-9 * solver.f_ref
        assert np.abs(x - x1).max() > 1e-4 * np.ptp(X)  # it moved
        x2, x1 = x1, x


@pytest.mark.parametrize("model", MODELS)
def test_fused_line_search_trial_takes_the_same_steps(model, monkeypatch):
    """The full-step trial that also builds the next Hessian (``fused_trial``) gives the same
    energy, gradient and matrix as the separate passes, so the trajectory is the same to the bit;
    and it is used (a broken fused pass would change the steps or never run)."""
    pot, X = scene(model)
    calls = []
    original = ImplicitEuler._evaluate_hessian

    def spy(self, *args):
        calls.append(1)
        return original(self, *args)

    monkeypatch.setattr(ImplicitEuler, "_evaluate_hessian", spy)
    runs = []
    for fused in (False, True):
        solver = ImplicitEuler(pot, NewtonSettings(tolerance=1e-9, fused_trial=fused))
        D = solver.dirichlet
        xs, needed, built = [X.copy(), X.copy()], 0, 0
        for t in range(2, 8):
            x, info = solver.step(xs[-1], xs[-2], X[D] + np.array([0.03 * t, 0.0, 0.02 * t]))
            xs.append(x)
            needed += info.iterations + info.projected
            built += info.hessians
        runs.append(np.stack(xs))
        # unfused, one Hessian pass per iteration (and per fallback to projection); fused, a trial
        # that converges or is rejected builds one more
        assert built == needed if not fused else built >= needed
        if not fused:
            assert not calls
    assert calls
    assert np.array_equal(runs[0], runs[1])
    assert np.abs(runs[0][-1] - X).max() > 1e-3  # it moved


# ---------------------------------------------------------------------------
# the compiled elastic energy of many states (the self-supervised losses)
# ---------------------------------------------------------------------------
def test_compiled_elastic_matches_the_terms_in_value_and_gradient(case):
    """potential.elastic through the kernels (with_compiled_elastic) against the terms' PyTorch
    energies under autograd, on a (2, 3) batch of states: same energies, same gradients."""
    _, pot, X, _ = case
    fast = kernels.with_compiled_elastic(pot)
    assert fast is not pot and fast.kernels is not None
    x0 = torch.as_tensor(np.stack(states(X, 4, count=6)).reshape(2, 3, *X.shape))
    xa, xb = x0.clone().requires_grad_(True), x0.clone().requires_grad_(True)
    ea, eb = pot.elastic(xa), fast.elastic(xb)
    assert eb.shape == (2, 3)
    w = torch.arange(1.0, 7.0, dtype=torch.float64).reshape(2, 3)  # a weighted sum: each state's gradient scaled
    (w * ea).sum().backward()
    (w * eb).sum().backward()
    assert close(eb.detach(), ea.detach())
    assert close(xb.grad, xa.grad)
    with torch.no_grad():  # the energy-only pass
        assert close(fast.elastic(x0), ea.detach())


def test_compiled_elastic_is_the_same_on_any_thread_count_and_refuses_second_derivatives(case):
    _, pot, X, ks = case
    x = np.stack(states(X, 5, count=5))
    E1, G1 = kernels.batch_energy_gradient(ks, x, threads=1)
    E2, G2 = kernels.batch_energy_gradient(ks, x, threads=2)
    assert np.array_equal(E1, E2) and np.array_equal(G1, G2)
    xt = torch.as_tensor(x).requires_grad_(True)
    # with another differentiable term beside it, a Hessian-vector product would silently miss the
    # elastic part (the kernels' gradient is a constant to autograd): it must raise instead
    total = (xt**2).sum() + kernels.compiled_energy(ks, xt).sum()
    with pytest.raises(RuntimeError, match="first derivatives only"):
        torch.autograd.grad(total, xt, create_graph=True)
    (g,) = torch.autograd.grad(total, xt)  # a first derivative is fine
    assert close(g, 2 * xt.detach() + torch.as_tensor(G1))
    with pytest.raises(ValueError, match="float64 CPU"):
        kernels.compiled_energy(ks, xt.detach().float())


LAWS = [("tets", "stvk"), ("tets", "neohookean"), ("tets", "stvk_nm"), ("shell", "stvk"), ("shell", "stvk_nm"), ("rods", "stvk")]


@pytest.mark.parametrize("model, law", LAWS)
def test_many_states_at_once_give_each_state_the_bits_of_a_one_state_pass(model, law, monkeypatch):
    """The energy kernels run blocks of states at once, the state index innermost (vectorised
    over the states); every state's energy, energy + gradient and energy-only pass are, to the
    bit, those of the one-state kernels the solver runs, for full and partial blocks."""
    monkeypatch.setattr(dispatch, "LANES", 4)  # 11 states: blocks of 4, 4 and 3
    pot, X = scene(model, law)
    ks = [kernels.term_kernel(t) for t in pot.terms]
    x = np.stack(states(X, 6, count=11))
    E, G = kernels.batch_energy_gradient(ks, x)
    E_only, _ = kernels.batch_energy_gradient(ks, x, gradient=False)
    for b in range(len(x)):
        g = np.zeros(x[b].size)
        assert E[b] == sum(k.energy_gradient(x[b], g) for k in ks)
        assert np.array_equal(G[b].reshape(-1), g)
        assert E_only[b] == sum(k.energy(x[b]) for k in ks)


def test_integrator_training_with_compiled_energies_follows_the_pytorch_one(monkeypatch):
    """fit_integrator on a tiny cloth simulated by the solver: with the compiled elastic energy
    (the default on the CPU) the self-supervised loss history is the PyTorch energy's to
    rounding, epoch by epoch, and the trained weights agree."""
    from latentsim.latent import Autoencoder, RelativeCoordinates, fit_integrator

    pot, X = scene("shell")
    solver = ImplicitEuler(pot, NewtonSettings(tolerance=1e-8))
    D = solver.dirichlet
    T = 14
    xD = np.stack([X[D] + [0.0, 0.0, 0.02 * t] for t in range(T)])
    xs = [X.copy(), X.copy()]
    for t in range(2, T):
        xs.append(solver.step(xs[-1], xs[-2], xD[t])[0])
    seq = {"positions": torch.as_tensor(np.stack(xs)), "dirichlet_positions": torch.as_tensor(xD), "bc": torch.full((T, 1), 0.6)}
    coords = RelativeCoordinates(len(X), D, "mean")
    ae = Autoencoder(coords.dim, 3, [16], pca_dim=3)
    ae.init_pca(coords.encode(seq["positions"], seq["dirichlet_positions"]))
    cfg = dict(widths=[16], epochs=3, lr=1e-3, batch_size=6)
    calls = []
    original = dispatch.batch_energy_gradient
    monkeypatch.setattr(dispatch, "batch_energy_gradient", lambda *a, **k: calls.append(1) or original(*a, **k))
    a, ha = fit_integrator(ae.eval(), coords, pot, [seq], cfg, seed=0, compiled=True)
    used = len(calls)
    b, hb = fit_integrator(ae.eval(), coords, pot, [seq], cfg, seed=0, compiled=False)
    assert used == 3 * 2 and len(calls) == used  # one call per batch (12 triplets, 2 batches) and epoch; none without
    assert np.allclose(ha["loss"], hb["loss"], rtol=1e-9, atol=0)
    assert all(torch.allclose(pa, pb, rtol=1e-6, atol=1e-9) for pa, pb in zip(a.parameters(), b.parameters()))


# ---------------------------------------------------------------------------
# two threads: vertex-disjoint halves of each term's stencils
# ---------------------------------------------------------------------------
def test_split_stencils_makes_vertex_disjoint_halves_and_a_thin_separator(case):
    model, pot, X, ks = case
    kernels.split_stencils(ks, len(X), threads=2)
    for k in ks:
        first, second, sep = k.groups
        assert np.array_equal(np.sort(np.concatenate(k.groups)), np.arange(len(k.stencils)))  # every stencil once
        assert not set(k.stencils[first].ravel()) & set(k.stencils[second].ravel())  # no shared vertex
        assert len(first) > 0 and len(second) > 0
        if model != "rods":  # a connected mesh: the separator is a layer, not a half
            assert len(sep) < 0.5 * len(k.stencils)


def test_solver_on_two_threads_gives_the_one_thread_result_bit_for_bit(case, monkeypatch):
    """The halves run concurrently (forced here on a small scene) and every path visits the
    groups in the same order, so the trajectory is identical to the serial one."""
    _, pot, X, _ = case
    monkeypatch.setattr(kernels.TermKernel, "MIN_PARALLEL", 0)
    runs = []
    for threads in (1, 2):
        solver = ImplicitEuler(pot, NewtonSettings(tolerance=1e-8), threads=threads)
        assert all(k.threads == threads and len(k.groups) == 3 for k in solver.assembly.kernels)
        D = solver.dirichlet
        xs = [X.copy(), X.copy()]
        for t in range(2, 8):
            xs.append(solver.step(xs[-1], xs[-2], X[D] + [0.0, 0.0, 0.01 * t])[0])
        runs.append(np.stack(xs))
    assert np.array_equal(runs[0], runs[1])
    assert np.abs(runs[0][-1] - X).max() > 1e-3  # it moved


def test_solver_energy_and_gradient_are_the_incremental_potentials(case):
    """The solver's compiled inertia + gravity + elastic pass (line search, initial guess) against
    the PyTorch incremental potential without the Dirichlet penalty, in value and autograd gradient;
    a wrong mass, time step or gravity sign in the inertia kernel fails it."""
    _, pot, X, _ = case
    solver = ImplicitEuler(pot, NewtonSettings())
    x, x1, x2 = states(X, 8)
    xt = torch.from_numpy(x.copy()).requires_grad_(True)
    e_ref = pot(xt, torch.from_numpy(x1), torch.from_numpy(x2), penalty=False)
    (g_ref,) = torch.autograd.grad(e_ref, xt)
    e_ref = e_ref.item()
    e, grad = solver._evaluate(x, x1, x2)
    assert abs(e - e_ref) <= 1e-10 * abs(e_ref)
    assert close(grad, g_ref.numpy().reshape(-1), 1e-10)
    assert abs(solver.energy(x, x1, x2) - e) <= 1e-12 * abs(e)
    grad_h, _ = solver.gradient_hessian(x, x1, x2, project=False)  # the Newton pass adds the same terms
    assert close(grad_h, grad, 1e-12)


def test_two_threads_give_the_same_bits_under_load(monkeypatch):
    """Energy, gradient and Hessian of a small tet scene on two threads (the halves forced to run
    concurrently), and the many-state energies on two threads, are bit for bit the same while
    two CPU-bound processes compete for the cores: static partitions, a fixed reduction order."""
    monkeypatch.setattr(kernels.TermKernel, "MIN_PARALLEL", 0)
    pot, X = scene("tets")
    ks = [kernels.term_kernel(t) for t in pot.terms]
    n = pot.n_vertices
    kernels.split_stencils(ks, n, threads=2)
    stencils = [k.stencils for k in ks]
    pattern = HessianPattern(n, stencils, np.arange(3 * n))
    slots = [pattern.stencil_slots(st) for st in stencils]
    xs = states(X, 9, count=4)

    def evaluate():
        out = []
        for x in xs:
            grad = np.zeros(3 * n)
            out += [np.array([sum(k.energy(x) for k in ks), sum(k.energy_gradient(x, grad) for k in ks)]), grad]
            for project in (False, True):
                grad, data = np.zeros(3 * n), np.zeros(pattern.nnz)
                e = sum(k.accumulate(x, grad, data, sl, project) for k, sl in zip(ks, slots))
                out += [np.array([e]), grad, data]
        out += list(kernels.batch_energy_gradient(ks, np.stack(xs), threads=2))
        return out

    idle = evaluate()
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        loaded = [evaluate() for _ in range(3)]
    finally:
        for p in busy:
            p.kill()
            p.wait()
    assert all(len(r) == len(idle) and all(np.array_equal(a, b) for a, b in zip(r, idle)) for r in loaded)
    assert all(np.abs(a).max() > 0 for a in idle)  # energies, gradients and Hessians really computed


def test_pair_distances_are_the_pytorch_distances():
    """The compiled contact distances (``kernels.distances``) equal ``primitives``' PyTorch ones to rounding, pair by
    pair and state by state, on random geometry and on each special case: a zero-length segment, parallel and collinear
    segments, segments that cross, a triangle of no area, a vertex on its triangle."""
    from latentsim.physics.kernels.distances import pair_distances, within
    from latentsim.physics.primitives import point_triangle_distance, segment_segment_distance

    rng = np.random.default_rng(11)
    x = rng.normal(size=(3, 40, 3))
    special = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0.5, 0.3, 0], [0.5, 0.3, 0], [3, 0, 0], [0.2, 0.2, 0], [0, 1, 0], [0.5, -0.3, 0]])
    x[:, :9] = special  # 0-1-2 collinear, 3 = 4 (a point as a segment), 6 on the triangle 0 1 7, 3-8 crosses 0-1
    fv = np.array([rng.choice(40, 4, replace=False) for _ in range(3000)] + [[3, 0, 1, 2], [6, 0, 1, 7], [5, 0, 1, 2]])
    ee = np.array([rng.choice(40, 4, replace=False) for _ in range(3000)]
                  + [[0, 1, 2, 5], [3, 4, 0, 1], [0, 1, 3, 8], [6, 3, 0, 2], [0, 7, 1, 3], [1, 2, 0, 5]])  # fmt: skip
    ids = np.concatenate([fv, ee])
    state = rng.integers(0, 3, len(ids))
    d = pair_distances(x, state, ids, len(fv))
    y = torch.as_tensor(x)[torch.as_tensor(state)[:, None], torch.as_tensor(ids)]
    ref = torch.cat([point_triangle_distance(y[: len(fv), 0], y[: len(fv), 1:]), segment_segment_distance(y[len(fv) :, :2], y[len(fv) :, 2:])]).numpy()
    assert np.abs(d - ref).max() <= 1e-14 * np.abs(x).max()
    assert d[len(fv) + 3000] == 1.0 and d[len(fv) + 3002] == 0.0 and d[3001] == 0.0  # collinear gap, crossing, on the face
    reach = np.median(ref)
    assert np.array_equal(within(x, state, ids, len(fv), reach), d < reach * (1 + 1e-6)) and (ref < reach).sum() == (d < reach).sum()


def test_self_pairs_are_every_pair_within_reach():
    """The compiled grid of self-contact (``kernels.distances.self_pairs``) finds exactly the pairs that measuring every
    vertex-triangle and edge-edge pair sharing no vertex finds within reach (by ``pair_distances``), at reaches from a
    fraction of a cell to several cells, on a crumpled sheet, on one with a vertex thrown 1e7 m away (beyond the grid's
    last cell on that axis) and on one scaled a thousandfold."""
    from latentsim.physics.kernels.distances import SLACK, pair_distances, self_pairs
    from latentsim.physics.mesh_contact import unique_edges

    X, tris = cloth_grid(7, 6, 0.2, 0.15, plane="xz")
    X, tris = np.asarray(X, np.float64), np.asarray(tris, np.int64)
    X[:, 1] = 0.03 * np.sin(25 * X[:, 0]) * np.cos(30 * X[:, 2]) + np.random.default_rng(5).normal(0, 0.004, len(X))
    edges = unique_edges(tris)
    fv = np.array([(v, *t) for v in range(len(X)) for t in tris if v not in t])
    ee = np.array([(*a, *b) for i, a in enumerate(edges) for b in edges[i + 1 :] if not set(a) & set(b)])
    far = X.copy()
    far[7] += (1e7, 0.0, 0.0)
    for x, reaches in ((X, (0.002, 0.01, 0.05, 0.12)), (far, (0.01, 0.05)), (X * 1000, (3.0, 50.0))):
        d_fv, d_ee = (pair_distances(x[None], np.zeros(len(p), np.int64), p, len(p) if p is fv else 0) for p in (fv, ee))
        for reach in reaches:
            ids, n_fv = self_pairs(x, tris, edges, reach)
            want_fv, want_ee = {tuple(p) for p in fv[d_fv < reach * (1 + SLACK)]}, {tuple(p) for p in ee[d_ee < reach * (1 + SLACK)]}
            assert {tuple(p) for p in ids[:n_fv]} == want_fv and {tuple(p) for p in ids[n_fv:]} == want_ee, reach
            assert len(ids) == len(want_fv) + len(want_ee)  # each pair once
        assert len(want_fv) > 5 and len(want_ee) > 5

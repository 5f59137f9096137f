"""Stable neo-Hookean tetrahedra (Smith, de Goes, Kim 2018): physics checks of energy, forces and Hessians.

The torch energy is the oracle (autograd); the compiled kernels must reproduce it.
"""

import math

import numpy as np
import pytest
import torch

from latentsim.mesh import beam_tets
from latentsim.physics.base import autograd_gradient_hessian, project_psd
from latentsim.physics.kernels.dispatch import batch_energy_gradient, term_kernel
from latentsim.physics.neohookean import StableNeoHookeanTets, snh_density, snh_parameters
from latentsim.physics.tets import StVKTets
from latentsim.scene import build_elastic, build_potential
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings

DT = torch.float64
YOUNG, NU = 1000.0, 0.3
MU_L, LAM_L = YOUNG / (2 * (1 + NU)), YOUNG * NU / ((1 + NU) * (1 - 2 * NU))

REGULAR = torch.tensor(
    [[1.0, 0.0, -1 / math.sqrt(2)], [-1.0, 0.0, -1 / math.sqrt(2)],
     [0.0, 1.0, 1 / math.sqrt(2)], [0.0, -1.0, 1 / math.sqrt(2)]], dtype=DT)  # fmt: skip


# --------------------------------------------------------------------------- helpers
def rotation(gen):
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=DT))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def random_tets(E, seed=0):
    """E disjoint well-shaped tets (random affine images of REGULAR), positively oriented."""
    gen = torch.Generator().manual_seed(seed)
    Xs = []
    for _ in range(E):
        M = rotation(gen) * (0.5 + torch.rand(1, generator=gen, dtype=DT))
        M = M @ (torch.eye(3, dtype=DT) + 0.25 * torch.randn(3, 3, generator=gen, dtype=DT))
        Xs.append(REGULAR @ M.T + torch.randn(1, 3, generator=gen, dtype=DT))
    X, T = torch.cat(Xs), torch.arange(4 * E).reshape(E, 4)
    neg = torch.linalg.det((X[T[:, 1:]] - X[T[:, :1]]).transpose(1, 2)) < 0  # swap two vertices of those
    T[neg, 1], T[neg, 2] = T[neg, 2].clone(), T[neg, 1].clone()
    return X, T


def beam(n=(4, 2, 2)):
    """A small tet beam with shared vertices (0.4 x 0.1 x 0.1 m)."""
    V, T = beam_tets(n[0], n[1], n[2], 0.4, 0.1, 0.1, tets_per_cell=5)
    return torch.as_tensor(V), torch.as_tensor(T)


def random_F(E, seed, kind):
    gen = torch.Generator().manual_seed(seed)
    F = torch.eye(3, dtype=DT) + 0.3 * torch.randn(E, 3, 3, generator=gen, dtype=DT)
    if kind == "inverted":
        F = F @ torch.diag(torch.tensor([1.0, 1.0, -0.5], dtype=DT))
    elif kind == "compressed":
        F = 0.6 * F
    elif kind == "stretched":
        F = 1.3 * F
    return F


def deform(term, X, F):
    """Element positions xe (E, 4, 3): element e mapped by F[e] plus a random translation."""
    Xe = term.gather(X)
    gen = torch.Generator().manual_seed(7)
    return torch.einsum("eij,eaj->eai", F, Xe) + torch.randn(Xe.shape[0], 1, 3, generator=gen, dtype=DT)


def rel(a, b):
    return ((a - b).norm() / b.norm()).item()


def f_space_projected_oracle(term, xe):
    """W B^T clamp(d^2 Psi / dF^2) B by autograd and a dense eigenvalue clamp of the 9x9 Hessian."""
    F = term.deformation_gradient(xe)

    def psi(f, m, l_):
        return snh_density(f.reshape(3, 3), m, l_)

    mu = term.mu.expand(len(F))
    lam = term.lam.expand(len(F))
    H9 = torch.stack([torch.func.hessian(psi)(F[e].reshape(9), mu[e], lam[e]) for e in range(len(F))])
    B = term.deformation_map()
    return term.rest_volume[:, None, None] * (B.transpose(1, 2) @ project_psd(H9) @ B)


# --------------------------------------------------------------------------- material
def test_reparametrised_lame_constants():
    mu, lam = snh_parameters(YOUNG, NU)
    assert mu == pytest.approx(4 / 3 * MU_L) and lam == pytest.approx(LAM_L + 5 / 6 * MU_L)
    term = StableNeoHookeanTets(*random_tets(1), YOUNG, NU)
    youngs, nu = term.youngs_poisson()
    assert float(youngs) == pytest.approx(YOUNG, rel=1e-14) and float(nu) == pytest.approx(NU, rel=1e-14)


# --------------------------------------------------------------------------- rest state
def test_rest_energy_is_zero_with_python_float_parameters():
    """snh_density(F, *snh_parameters(E, nu)) with plain numbers: alpha and Psi(I) are computed in float64, so
    that they cancel the rest energy to rounding (in float32 they left up to 0.0188 Pa)."""
    for youngs in (1.0e3, 3.0e5, 1.0e6, 1.0e7):
        mu, lam = snh_parameters(youngs, NU)
        assert isinstance(mu, float) and isinstance(lam, float)
        psi = snh_density(torch.eye(3, dtype=DT), mu, lam)
        assert psi.dtype == DT and abs(float(psi)) < 1e-15 * (mu + lam)
        assert float(snh_density(torch.eye(3, dtype=DT), torch.tensor(mu, dtype=DT), torch.tensor(lam, dtype=DT))) == float(psi)


@pytest.mark.parametrize("mesh", ["random", "beam"])
def test_rest_state_has_zero_energy_and_force(mesh):
    X, T = random_tets(6) if mesh == "random" else beam()
    term = StableNeoHookeanTets(X, T, YOUNG, NU)
    xe = term.gather(X)
    scale = (MU_L + LAM_L) * term.rest_volume.max().item()
    assert term.element_energy(X).abs().max().item() < 1e-13 * scale
    g_ref, _ = term.local_gradient_hessian(1.01 * xe)
    for project in (True, False):
        g, _ = term.local_gradient_hessian(xe, project=project)
        assert g.abs().max().item() < 1e-12 * g_ref.abs().max().item()
    assert term.stress_norm(X).max().item() < 1e-12 * (MU_L + LAM_L)
    # at rest the Hessian is PSD: the projection changes nothing
    _, Hp = term.local_gradient_hessian(xe, project=True)
    _, He = term.local_gradient_hessian(xe, project=False)
    assert rel(Hp, He) < 1e-12


def test_energy_is_invariant_under_rigid_motion():
    X, T = random_tets(5, seed=1)
    term = StableNeoHookeanTets(X, T, YOUNG, NU)
    gen = torch.Generator().manual_seed(3)
    for kind in ("stretched", "compressed", "inverted"):
        xe = deform(term, X, random_F(5, 2, kind))
        e0 = term.local_energy(xe)
        assert e0.abs().min() > 1e-3 * (MU_L + LAM_L) * term.rest_volume.min()  # a real deformation
        for _ in range(3):
            R, t = rotation(gen), torch.randn(3, generator=gen, dtype=DT)
            e1 = term.local_energy(xe @ R.T + t)
            assert rel(e1, e0) < 1e-12
    # the rest state moved rigidly (a proper rotation) has zero energy too
    R = rotation(gen)
    assert term.element_energy(X @ R.T + 1.0).abs().max() < 1e-12 * (MU_L + LAM_L) * term.rest_volume.max()


# --------------------------------------------------------------------------- derivatives
@pytest.mark.parametrize("kind", ["stretched", "compressed", "inverted"])
def test_gradient_matches_central_differences(kind):
    X, T = random_tets(3, seed=4)
    term = StableNeoHookeanTets(X, T, YOUNG, NU)
    xe = deform(term, X, random_F(3, 5, kind))
    g, _ = term.local_gradient_hessian(xe, project=False)
    h = 1e-6
    fd = torch.zeros_like(g)
    for j in range(12):
        d = torch.zeros(12, dtype=DT)
        d[j] = h
        d = d.reshape(4, 3)
        fd[:, j] = (term.local_energy(xe + d) - term.local_energy(xe - d)) / (2 * h)
    assert rel(g, fd) < 1e-7


@pytest.mark.parametrize("kind", ["stretched", "compressed", "inverted"])
def test_exact_hessian_and_gradient_match_autograd(kind):
    X, T = random_tets(8, seed=6)
    term = StableNeoHookeanTets(X, T, YOUNG, NU)
    xe = deform(term, X, random_F(8, 9, kind))
    g, H = term.local_gradient_hessian(xe, project=False)
    ga, Ha = autograd_gradient_hessian(term, xe, project=False)
    assert rel(g, ga) < 1e-12
    assert rel(H, Ha) < 1e-12


@pytest.mark.parametrize("kind", ["stretched", "compressed", "inverted"])
def test_projected_hessian_is_psd_and_the_f_space_clamp(kind):
    X, T = random_tets(8, seed=10)
    term = StableNeoHookeanTets(X, T, YOUNG, NU)
    xe = deform(term, X, random_F(8, 11, kind))
    _, Hp = term.local_gradient_hessian(xe, project=True)
    _, He = term.local_gradient_hessian(xe, project=False)
    scale = He.abs().amax((1, 2))
    assert (torch.linalg.eigvalsh(Hp).amin(1) > -1e-12 * scale).all()
    # the analytic eigensystem, clamped, is the clamp of the dense F-space Hessian
    assert rel(Hp, f_space_projected_oracle(term, xe)) < 1e-10
    # where the exact Hessian is PSD, the projection leaves it unchanged (and it is not everywhere)
    psd = torch.linalg.eigvalsh(He).amin(1) > -1e-12 * scale
    for e in torch.nonzero(psd).flatten():
        assert rel(Hp[e], He[e]) < 1e-10
    if kind == "inverted":
        assert not psd.all()


def test_projected_hessian_at_a_stretch_where_the_exact_one_is_psd():
    """Pure mild stretches: dP/dF is positive definite, so projection is the identity."""
    X, T = random_tets(4, seed=12)
    term = StableNeoHookeanTets(X, T, YOUNG, NU)
    gen = torch.Generator().manual_seed(13)
    F = torch.stack([rotation(gen) @ torch.diag(1.05 + 0.1 * torch.rand(3, generator=gen, dtype=DT)) for _ in range(4)])
    xe = deform(term, X, F)
    _, Hp = term.local_gradient_hessian(xe, project=True)
    _, He = term.local_gradient_hessian(xe, project=False)
    assert (torch.linalg.eigvalsh(He).amin(1) > -1e-9 * He.abs().amax((1, 2))).all()
    assert rel(Hp, He) < 1e-10


# --------------------------------------------------------------------------- small strain
def test_small_strain_limit_is_linear_elasticity():
    """At rest the Hessian equals StVK's (both are linear elasticity with E, nu), and for small
    strains the energies agree to first order in the strain."""
    X, T = random_tets(6, seed=14)
    snh, stvk = StableNeoHookeanTets(X, T, YOUNG, NU), StVKTets(X, T, YOUNG, NU)
    xe = snh.gather(X)
    _, H1 = snh.local_gradient_hessian(xe, project=False)
    _, H2 = stvk.local_gradient_hessian(xe, project=False)
    assert rel(H1, H2) < 1e-12
    gen = torch.Generator().manual_seed(15)
    G = torch.randn(6, 3, 3, generator=gen, dtype=DT)
    errs = []
    for t in (1e-3, 1e-4):
        F = torch.eye(3, dtype=DT) + t * G
        e1, e2 = snh.local_energy(deform(snh, X, F)), stvk.local_energy(deform(stvk, X, F))
        # linear elasticity by hand: mu ||eps||^2 + lam/2 tr(eps)^2 with eps = sym(F - I)
        eps = 0.5 * (t * G + t * G.transpose(1, 2))
        lin = snh.rest_volume * (MU_L * (eps * eps).sum((1, 2)) + 0.5 * LAM_L * eps.diagonal(dim1=1, dim2=2).sum(1) ** 2)
        errs.append(rel(e1, lin))
        assert rel(e2, lin) < 10 * t  # StVK's own small-strain limit
    assert errs[0] < 10 * 1e-3 and errs[1] < 10 * 1e-4
    assert errs[1] < 0.2 * errs[0]  # the difference is O(strain): it shrinks with it


# --------------------------------------------------------------------------- inversion
@pytest.mark.parametrize("F", [
    torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=DT)),  # the rest state reflected
    torch.diag(torch.tensor([0.8, 1.1, -0.3], dtype=DT)),
    torch.tensor([[1.0, 0.2, 0.1], [0.0, 0.9, 0.3], [0.1, 0.0, -0.2]], dtype=DT),
    torch.diag(torch.tensor([1.0, 1.2, 0.0], dtype=DT)),  # flattened to zero volume
], ids=["reflection", "inverted", "inverted_sheared", "flattened"])
def test_inverted_tet_has_finite_energy_and_a_restoring_force(F):
    X, T = random_tets(1, seed=16)
    term = StableNeoHookeanTets(X, T, YOUNG, NU)
    xe = deform(term, X, F[None])
    assert torch.linalg.det(term.deformation_gradient(xe)).item() <= 0
    energy = term.local_energy(xe)
    assert torch.isfinite(energy).all() and energy.item() > 0
    g, H = term.local_gradient_hessian(xe, project=False)
    assert torch.isfinite(g).all() and torch.isfinite(H).all()
    # moving along the force -g raises det F: the element is pushed back towards positive volume
    # dJ/dx_a = (cof F) D_a, cof F = dJ/dF with columns f1 x f2, f2 x f0, f0 x f1
    Fd = term.deformation_gradient(xe)[0]
    cof = torch.stack([torch.linalg.cross(Fd[:, (j + 1) % 3], Fd[:, (j + 2) % 3], dim=0) for j in range(3)], 1)
    dJ = (term.grad_op[0] @ cof.T)[None]
    assert (-g.reshape(1, 4, 3) * dJ).sum().item() > 0
    # StVK has no such force at the reflection: it sees the mirrored rest state as at rest
    if F[2, 2] == -1.0 and F[0, 0] == 1.0:
        assert StVKTets(X, T, YOUNG, NU).local_energy(xe).abs().item() < 1e-12


def test_gradient_flow_uninverts_a_tet():
    """Projected Newton on one tet with three vertices held: the fourth, pushed through the
    opposite face, comes back and the tet ends at rest with positive volume."""
    X, T = random_tets(1, seed=17)
    term = StableNeoHookeanTets(X, T, YOUNG, NU)
    x = X.clone()
    n = torch.linalg.cross(X[2] - X[1], X[3] - X[1])
    x[0] = X[0] + 2.0 * (n @ (X[1] - X[0])) / (n @ n) * n  # vertex 0 mirrored through face (1, 2, 3)
    assert torch.linalg.det(term.deformation_gradient(term.gather(x))).item() < 0
    for _ in range(50):
        g, H = term.local_gradient_hessian(term.gather(x), project=True)
        step = torch.linalg.solve(H[0, :3, :3] + 1e-12 * torch.eye(3, dtype=DT), g[0, :3])
        alpha, e0 = 1.0, term.energy(x)
        while True:
            trial = x.clone()
            trial[0] -= alpha * step
            if term.energy(trial) < e0 or alpha < 1e-8:
                break
            alpha *= 0.5
        x = trial
    assert torch.linalg.det(term.deformation_gradient(term.gather(x))).item() > 0
    assert (x - X).abs().max().item() < 1e-6


# --------------------------------------------------------------------------- compiled kernels
def test_compiled_kernels_equal_the_torch_oracle():
    X, T = beam()
    term = StableNeoHookeanTets(X, T, YOUNG, NU)
    gen = torch.Generator().manual_seed(18)
    states = torch.stack([X + 0.03 * torch.randn(X.shape, generator=gen, dtype=DT) for _ in range(3)])
    states[2, :, 1] *= -1.0  # mirrored: every element inverted
    k = term_kernel(term)
    E, G = batch_energy_gradient([k], states.numpy())
    for b in range(3):
        x = states[b].clone().requires_grad_(True)
        e = term.energy(x)
        (g,) = torch.autograd.grad(e, x)
        assert abs(k.energy(states[b].numpy()) - e.item()) <= 1e-12 * abs(e.item())
        assert abs(E[b] - e.item()) <= 1e-12 * abs(e.item())
        assert rel(torch.from_numpy(G[b]), g) < 1e-12


def test_weighted_subset_is_the_weighted_sum_of_element_energies():
    X, T = beam()
    term = StableNeoHookeanTets(X, T, YOUNG, NU)
    gen = torch.Generator().manual_seed(19)
    x = X + 0.05 * torch.randn(X.shape, generator=gen, dtype=DT)
    idx = np.array([0, 3, 7, 11, 30])
    w = np.array([0.5, 2.0, 1.0, 3.5, 0.0])
    sub = term.weighted_subset(idx, w)
    assert isinstance(sub, StableNeoHookeanTets)
    expected = (torch.as_tensor(w) * term.element_energy(x)[idx]).sum()
    assert sub.energy(x).item() == pytest.approx(expected.item(), rel=1e-12)
    assert term_kernel(sub).energy(x.numpy()) == pytest.approx(expected.item(), rel=1e-12)


# --------------------------------------------------------------------------- scene and simulation
def test_scene_material_model_selects_the_energy():
    V, T = beam_tets(2, 1, 1, 0.2, 0.1, 0.1, tets_per_cell=5)
    arrays = {"rest_positions": V, "tets": T, "dirichlet": np.array([0])}
    mat = {"youngs_modulus": YOUNG, "poisson_ratio": NU, "density": 1000.0}
    assert type(build_elastic("tets", arrays, mat).terms[0]) is StVKTets
    assert type(build_elastic("tets", arrays, {**mat, "model": "stvk"}).terms[0]) is StVKTets
    assert type(build_elastic("tets", arrays, {**mat, "model": "neohookean"}).terms[0]) is StableNeoHookeanTets
    with pytest.raises(ValueError, match="material.model 'rubber'"):
        build_elastic("tets", arrays, {**mat, "model": "rubber"})


def test_implicit_euler_beam_converges_and_matches_stvk_at_small_strain():
    """A clamped beam falls under gravity for a few frames: every Newton solve converges (its
    residual is rechecked here by autograd), and at this small strain the motion is StVK's."""
    V, T = beam_tets(4, 1, 1, 0.4, 0.1, 0.1, tets_per_cell=5)
    D = np.flatnonzero(V[:, 0] < 1e-12)
    arrays = {"rest_positions": V, "tets": T, "dirichlet": D}
    free = np.setdiff1d(np.arange(len(V)), D)
    runs = {}
    for model, youngs in (("neohookean", 5e5), ("stvk", 5e5), ("neohookean", 3e3)):
        mat = {"youngs_modulus": youngs, "poisson_ratio": 0.3, "density": 1000.0, "model": model}
        pot = build_potential("tets", arrays, mat, 1 / 30, [0.0, -9.81, 0.0], w_bc=1e4)
        solver = ImplicitEuler(pot, NewtonSettings(tolerance=1e-8, max_iterations=50))
        xs = [V.copy(), V.copy()]
        for _ in range(8):
            x, info = solver.step(xs[-1], xs[-2], V[D])
            xt = torch.as_tensor(x).requires_grad_(True)
            (g,) = torch.autograd.grad(pot(xt, torch.as_tensor(xs[-1]), torch.as_tensor(xs[-2]), penalty=False), xt)
            assert g[free].norm().item() <= 1e-8 * solver.f_ref
            xs.append(x)
        runs[(model, youngs)] = np.array(xs)
    sag = np.abs(runs[("stvk", 5e5)][-1] - V).max()
    assert sag > 0.01  # the beam really moves
    assert np.abs(runs[("neohookean", 5e5)] - runs[("stvk", 5e5)]).max() < 0.02 * sag
    soft = runs[("neohookean", 3e3)]  # large deformation: the soft beam hangs down
    assert np.abs(soft[-1] - V).max() > 5 * sag
    vol = torch.linalg.det(torch.as_tensor(soft[-1])[T[:, 1:]] - torch.as_tensor(soft[-1])[T[:, :1]])
    assert (vol > 0).all()


def test_volume_ratios_give_det_f_and_count_inverted_tets():
    """Uniform scaling by s gives det F = s^3 on every tet; a vertex pushed through its opposite face inverts
    exactly the tets that hold it."""
    from latentsim.stages.simulate import volume_ratios

    V, T = beam_tets(2, 1, 1, 0.2, 0.1, 0.1, tets_per_cell=5)
    flipped = V.copy()
    k = int(np.argmax(np.bincount(T.ravel())))  # the vertex in the most tets
    holders = np.flatnonzero((T == k).any(axis=1))
    # reflect vertex k through the plane of the opposite face of its first tet, far enough to invert that tet
    t = T[holders[0]]
    a, b, c = V[[v for v in t if v != k]]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    flipped[k] = V[k] - 2.5 * np.dot(V[k] - a, n) * n
    min_ratio, inverted = volume_ratios(np.stack([V, 1.5 * V, flipped]), V, T)
    assert min_ratio[0] == pytest.approx(1.0) and min_ratio[1] == pytest.approx(1.5**3)
    assert inverted[0] == inverted[1] == 0
    assert 1 <= inverted[2] <= len(holders) and min_ratio[2] < 0

"""St. Venant-Kirchhoff tetrahedra: physics checks of energy, forces, Hessians, stress, masses."""

import math

import numpy as np
import pytest
import torch

from latentsim.physics.base import autograd_gradient_hessian, project_psd
from latentsim.physics.kernels.core import rotation_variant_svd
from latentsim.physics.tets import StVKTets, lame, lumped_masses

DT = torch.float64
YOUNG, NU = 1000.0, 0.3
MU, LAM = YOUNG / (2 * (1 + NU)), YOUNG * NU / ((1 + NU) * (1 - 2 * NU))

# a regular tetrahedron, positively oriented (det [X1-X0, X2-X0, X3-X0] > 0)
REGULAR = torch.tensor(
    [[1.0, 0.0, -1 / math.sqrt(2)], [-1.0, 0.0, -1 / math.sqrt(2)],
     [0.0, 1.0, 1 / math.sqrt(2)], [0.0, -1.0, 1 / math.sqrt(2)]], dtype=DT)


# --------------------------------------------------------------------------- helpers
def rotation(gen):
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=DT))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def orient(X, tets):
    """Swap two vertices of negatively oriented tets."""
    tets = tets.clone()
    Dm = X[tets[:, 1:]] - X[tets[:, :1]]
    neg = torch.linalg.det(Dm) < 0
    tets[neg, 1], tets[neg, 2] = tets[neg, 2].clone(), tets[neg, 1].clone()
    return tets


def random_tets(E, seed=0, regular=False):
    """E disjoint well-shaped tets: random affine (or similarity) images of REGULAR."""
    gen = torch.Generator().manual_seed(seed)
    Xs = []
    for _ in range(E):
        M = rotation(gen) * (0.5 + torch.rand(1, generator=gen, dtype=DT))
        if not regular:
            M = M @ (torch.eye(3, dtype=DT) + 0.25 * torch.randn(3, 3, generator=gen, dtype=DT))
        Xs.append(REGULAR @ M.T + torch.randn(1, 3, generator=gen, dtype=DT))
    X = torch.cat(Xs)
    return X, orient(X, torch.arange(4 * E).reshape(E, 4))


def grid(m, jitter=0.0, seed=0):
    """Unit cube cut into m^3 cubes of 6 (Freudenthal) tets; jitter moves interior vertices."""
    g = torch.arange(m + 1, dtype=DT) / m
    X = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    idx = torch.arange((m + 1) ** 3).reshape(m + 1, m + 1, m + 1)
    corners = torch.stack(torch.meshgrid(*[torch.arange(m)] * 3, indexing="ij"), -1).reshape(-1, 3)
    tets = []
    for perm in ([0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]):
        e = torch.eye(3, dtype=torch.long)
        vs = [corners, corners + e[perm[0]], corners + e[perm[0]] + e[perm[1]], corners + 1]
        tets.append(torch.stack([idx[v[:, 0], v[:, 1], v[:, 2]] for v in vs], 1))
    tets = torch.cat(tets)
    interior = ((X > 0) & (X < 1)).all(1)
    if jitter:
        gen = torch.Generator().manual_seed(seed)
        X = X + jitter / m * interior[:, None] * (torch.rand(X.shape, generator=gen, dtype=DT) - 0.5)
    return X, orient(X, tets), interior


def deform(term, X, F_list, seed=0, noise=0.0):
    """Element positions xe (E, 4, 3): element e mapped by F_list[e] plus a translation."""
    gen = torch.Generator().manual_seed(seed)
    Xe = term.gather(X)
    xe = torch.einsum("eij,eaj->eai", F_list, Xe) + torch.randn(Xe.shape[0], 1, 3, generator=gen, dtype=DT)
    return xe + noise * torch.randn(xe.shape, generator=gen, dtype=DT)


def random_F(E, seed, kind):
    gen = torch.Generator().manual_seed(seed)
    F = torch.eye(3, dtype=DT) + 0.3 * torch.randn(E, 3, 3, generator=gen, dtype=DT)
    if kind == "inverted":  # reflect: det F < 0
        F = F @ torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=DT))
        F[:, :, 2] *= 0.5
    elif kind == "compressed":  # some eigenvalues of dP/dF negative, some positive
        F = 0.75 * F
    elif kind == "crushed":  # every eigenvalue of dP/dF negative: projects to zero
        F = 0.4 * F
    elif kind == "stretched":  # mild, pure stretch: dP/dF is positive definite
        F = torch.diag_embed(1.1 + 0.1 * torch.rand(E, 3, generator=gen, dtype=DT))
        F = torch.stack([rotation(gen) @ f for f in F])
    return F


def assemble(term, g, n):
    return torch.zeros(n, 3, dtype=g.dtype).index_add_(0, term.stencils.reshape(-1), g.reshape(-1, 3))


def rel(a, b):
    return ((a - b).norm() / b.norm()).item()


def psi_by_hand(A, mu, lam):
    """Psi(A) = mu ||E||^2 + lam/2 tr(E)^2, E = (A^T A - I)/2, in plain NumPy."""
    E = 0.5 * (A.T @ A - np.eye(3))
    return mu * np.sum(E * E) + 0.5 * lam * np.trace(E) ** 2


# --------------------------------------------------------------------------- material
def test_lame_parameters():
    mu, lam = lame(2.5, 0.25)
    assert mu == pytest.approx(1.0) and lam == pytest.approx(1.0)
    mu, lam = lame(YOUNG, NU)
    assert mu == pytest.approx(MU) and lam == pytest.approx(LAM)
    with pytest.raises(ValueError):
        lame(1.0, 0.5)


# --------------------------------------------------------------------------- rest state
@pytest.mark.parametrize("mesh", ["random", "grid"])
def test_rest_state_has_zero_energy_gradient_and_stress(mesh):
    X, tets = random_tets(6) if mesh == "random" else grid(2)[:2]
    term = StVKTets(X, tets, YOUNG, NU)
    xe = term.gather(X)
    scale = (MU + LAM) * term.rest_volume.max().item()
    assert term.element_energy(X).abs().max().item() < 1e-13 * scale
    # forces at 1% stretch set the scale the rest forces must vanish against
    g_ref, _ = term.local_gradient_hessian(1.01 * xe)
    for project in (True, False):
        g, H = term.local_gradient_hessian(xe, project=project)
        assert g.abs().max().item() < 1e-12 * g_ref.abs().max().item()
    assert term.stress_norm(X).abs().max().item() < 1e-12 * (MU + LAM)
    # at rest dP/dF is PSD (its twist eigenvalues are exactly 0): projection changes nothing
    _, Hp = term.local_gradient_hessian(xe, project=True)
    _, He = term.local_gradient_hessian(xe, project=False)
    assert rel(Hp, He) < 1e-12


# --------------------------------------------------------------------------- invariances
def test_energy_is_invariant_under_rigid_motion():
    X, tets = random_tets(8, seed=1)
    term = StVKTets(X, tets, YOUNG, NU)
    xe = deform(term, X, random_F(8, 2, "generic"))
    gen = torch.Generator().manual_seed(3)
    R, t = rotation(gen), torch.randn(3, generator=gen, dtype=DT)
    xr = xe @ R.T + t
    e0, e1 = term.local_energy(xe), term.local_energy(xr)
    assert e0.abs().min().item() > 1e-3  # deformed: a real test
    assert torch.allclose(e1, e0, rtol=1e-12, atol=0)
    # objectivity of stress and of the compiled derivatives: P -> R P, g -> R g, H -> R H R^T
    n = X.shape[0]
    P0 = term.first_piola(xe.reshape(n, 3))
    P1 = term.first_piola(xr.reshape(n, 3))
    assert torch.allclose(P1, R @ P0, rtol=0, atol=1e-10 * P0.abs().max().item())
    RR = torch.block_diag(R, R, R, R)
    for project in (True, False):
        g0, H0 = term.local_gradient_hessian(xe, project=project)
        g1, H1 = term.local_gradient_hessian(xr, project=project)
        assert rel(g1, g0 @ RR.T) < 1e-12
        assert rel(H1, RR @ H0 @ RR.T) < 1e-10


# --------------------------------------------------------------------------- derivatives
def test_gradient_matches_central_differences():
    X, tets, _ = grid(2, jitter=0.3)
    term = StVKTets(X, tets, YOUNG, NU)
    gen = torch.Generator().manual_seed(4)
    x = X @ (torch.eye(3, dtype=DT) + 0.2 * torch.randn(3, 3, generator=gen, dtype=DT)).T
    x = x + 0.05 * torch.randn(x.shape, generator=gen, dtype=DT)
    n = X.shape[0]
    g, _ = term.local_gradient_hessian(term.gather(x))
    g = assemble(term, g, n).reshape(-1)
    h = 1e-5
    flat = x.reshape(-1)
    fd = torch.empty_like(flat)
    for i in range(flat.numel()):
        xp, xm = flat.clone(), flat.clone()
        xp[i] += h
        xm[i] -= h
        fd[i] = (term.energy(xp.reshape(n, 3)) - term.energy(xm.reshape(n, 3))) / (2 * h)
    assert rel(g, fd) < 1e-6


STATES = ["generic", "inverted", "compressed", "crushed", "stretched"]


@pytest.mark.parametrize("kind", STATES)
def test_exact_hessian_matches_autograd(kind):
    X, tets = random_tets(10, seed=5)
    term = StVKTets(X, tets, YOUNG, NU)
    xe = deform(term, X, random_F(10, 6, kind))
    g, H = term.local_gradient_hessian(xe, project=False)
    g0, H0 = autograd_gradient_hessian(term, xe, project=False)
    assert rel(g, g0) < 1e-10
    assert rel(H, H0) < 1e-8


def _f_space_projected_oracle(term, xe):
    """W B^T project_psd(d^2 Psi / dF^2) B, with the 9x9 Hessian by autograd."""
    F = term.deformation_gradient(xe).reshape(-1, 9)

    def psi(f):
        f = f.reshape(3, 3)
        E = 0.5 * (f.T @ f - torch.eye(3, dtype=DT))
        return term.mu * (E * E).sum() + 0.5 * term.lam * torch.trace(E) ** 2

    Hf = torch.vmap(torch.func.hessian(psi))(F)
    B = term.deformation_map()
    return term.rest_volume[:, None, None] * B.transpose(1, 2) @ project_psd(Hf) @ B, Hf


@pytest.mark.parametrize("kind", STATES)
def test_projected_hessian_matches_oracles_and_is_psd(kind):
    # general tets: the F-space projection (Teran et al.) is the unique reference;
    # errors are measured against the size of the exact Hessian
    X, tets = random_tets(10, seed=7)
    term = StVKTets(X, tets, YOUNG, NU)
    xe = deform(term, X, random_F(10, 8, kind))
    _, H = term.local_gradient_hessian(xe, project=True)
    _, H_exact = term.local_gradient_hessian(xe, project=False)
    H_ref, Hf = _f_space_projected_oracle(term, xe)
    scale = H_exact.norm()
    assert (H - H_ref).norm() < 1e-8 * scale
    ev = torch.linalg.eigvalsh(H)
    assert (ev.min(1).values >= -1e-9 * torch.linalg.matrix_norm(H_exact, ord=2)).all()
    indefinite = (torch.linalg.eigvalsh(Hf).min(1).values < 0).any().item()
    assert indefinite == (kind != "stretched")  # the projection is really exercised
    assert (H.abs().amax((1, 2)) > 0).all() == (kind != "crushed")
    if kind == "stretched":  # PD everywhere: projected == exact == 12x12-projected oracle
        _, H0 = autograd_gradient_hessian(term, xe, project=True)
        assert (H - H0).norm() < 1e-8 * scale

    # regular tets (D^T D ~ I): F-space and 12x12 projections coincide -> base oracle
    X, tets = random_tets(10, seed=9, regular=True)
    term = StVKTets(X, tets, YOUNG, NU)
    xe = deform(term, X, random_F(10, 10, kind))
    _, H = term.local_gradient_hessian(xe, project=True)
    _, H0 = autograd_gradient_hessian(term, xe, project=True)
    _, H_exact = term.local_gradient_hessian(xe, project=False)
    assert (H - H0).norm() < 1e-8 * H_exact.norm()


def test_projected_hessian_at_inversion_and_collapse_is_the_f_space_clamp():
    """Every tet of a mesh inverted, some flattened onto a plane: the compiled SVD-based clamp
    is the F-space oracle (autograd d^2 Psi / dF^2, eigenvalue-clamped), and PSD."""
    X, tets, _ = grid(2, jitter=0.3)
    term = StVKTets(X, tets, YOUNG, NU)
    x = X.clone()
    x[:, 2] *= -0.6  # every tet inverted
    x[:5, 1] = x[:5, 1].mean()  # some flattened
    xe = term.gather(x)
    _, H = term.local_gradient_hessian(xe, project=True)
    _, H_exact = term.local_gradient_hessian(xe, project=False)
    H_ref, _ = _f_space_projected_oracle(term, xe)
    assert (H - H_ref).norm() < 1e-8 * H_exact.norm()
    assert (torch.linalg.eigvalsh(H).min(1).values >= -1e-9 * torch.linalg.matrix_norm(H_exact, ord=2)).all()


def test_rotation_variant_svd():
    gen = torch.Generator().manual_seed(11)
    F = torch.randn(64, 3, 3, generator=gen, dtype=DT)
    F[0] = torch.eye(3, dtype=DT)  # repeated singular values
    F[1] = torch.diag(torch.tensor([2.0, 1.0, 0.0], dtype=DT))  # flat element
    F[2] = -torch.eye(3, dtype=DT)  # inverted
    U, s, V = (torch.from_numpy(a) for a in rotation_variant_svd(F.numpy()))
    assert torch.allclose(U @ torch.diag_embed(s) @ V.transpose(1, 2), F, atol=1e-13)
    assert torch.allclose(torch.linalg.det(U), torch.ones(64, dtype=DT), atol=1e-13)
    assert torch.allclose(torch.linalg.det(V), torch.ones(64, dtype=DT), atol=1e-13)
    assert torch.equal(s[:, 2] < 0, torch.linalg.det(F) < 0)
    assert torch.allclose(s.abs(), torch.linalg.svdvals(F), atol=1e-13)


# --------------------------------------------------------------------------- patch test
def test_patch_test_affine_deformation():
    X, tets, interior = grid(3, jitter=0.4, seed=12)
    assert interior.sum() == 8
    term = StVKTets(X, tets, YOUNG, NU)
    A = np.array([[1.2, 0.1, -0.05], [0.03, 0.9, 0.2], [-0.1, 0.05, 1.1]])
    b = np.array([0.3, -1.0, 2.0])
    x = X @ torch.tensor(A).T + torch.tensor(b)
    total_volume = 1.0  # unit cube
    assert term.energy(x).item() == pytest.approx(total_volume * psi_by_hand(A, MU, LAM), rel=1e-12)
    g, _ = term.local_gradient_hessian(term.gather(x))
    f = assemble(term, g, X.shape[0]).norm(dim=1)
    assert f[~interior].max() > 1.0  # boundary tractions are there...
    assert f[interior].max() < 1e-10 * f[~interior].max()  # ...interior forces balance


# --------------------------------------------------------------------------- stress
def test_first_piola_uniaxial_stretch():
    X, tets = random_tets(3, seed=13)
    term = StVKTets(X, tets, YOUNG, NU)
    s = 1.3
    x = X @ torch.diag(torch.tensor([s, 1.0, 1.0], dtype=DT))
    P = term.first_piola(x)
    e11 = 0.5 * (s * s - 1.0)  # Green strain, the only nonzero component
    P_ref = torch.diag(torch.tensor([s * (2 * MU + LAM) * e11, LAM * e11, LAM * e11], dtype=DT))
    assert torch.allclose(P, P_ref.expand(3, 3, 3), rtol=1e-12, atol=1e-9)
    norm_ref = math.sqrt((s * (2 * MU + LAM) * e11) ** 2 + 2 * (LAM * e11) ** 2)
    assert torch.allclose(term.stress_norm(x), torch.full((3,), norm_ref, dtype=DT), rtol=1e-12)
    # batched over leading axes
    xb = torch.stack([X, x])
    assert term.stress_norm(xb).shape == (2, 3)
    assert term.stress_norm(xb)[0].abs().max().item() < 1e-12 * norm_ref


# --------------------------------------------------------------------------- batching
def test_local_energy_batching():
    X, tets, _ = grid(2, jitter=0.3)
    term = StVKTets(X, tets, YOUNG, NU)
    gen = torch.Generator().manual_seed(14)
    xs = X + 0.1 * torch.randn(5, *X.shape, generator=gen, dtype=DT)
    xe = term.gather(xs)  # (5, E, 4, 3)
    batched = term.local_energy(xe)
    separate = torch.stack([term.local_energy(xe[i]) for i in range(5)])
    assert batched.shape == (5, tets.shape[0])
    assert torch.allclose(batched, separate, rtol=1e-14, atol=0)
    deeper = term.energy(xs.reshape(5, 1, *X.shape).expand(5, 2, *X.shape))
    assert torch.allclose(deeper, separate.sum(-1)[:, None].expand(5, 2), rtol=1e-14)
    # differentiable through the batch: per-sample gradients equal the compiled one
    xs.requires_grad_(True)
    (grad,) = torch.autograd.grad(term.energy(xs).sum(), xs)
    g, _ = term.local_gradient_hessian(xe[3].detach())
    assert rel(grad[3], assemble(term, g, X.shape[0])) < 1e-12


# --------------------------------------------------------------------------- masses
def test_lumped_masses():
    X, tets, _ = grid(2, jitter=0.3)
    rho = 1070.0
    m = lumped_masses(X, tets, rho)
    assert m.shape == (X.shape[0],) and (m > 0).all()
    assert m.sum().item() == pytest.approx(rho * 1.0, rel=1e-12)  # unit cube
    Xt, tt = random_tets(1, seed=15)
    vol = abs(torch.linalg.det(Xt[1:] - Xt[:1]).item()) / 6.0
    assert torch.allclose(lumped_masses(Xt, tt, rho), torch.full((4,), rho * vol / 4, dtype=DT))
    rho_e = torch.linspace(500.0, 1500.0, tets.shape[0], dtype=DT)
    vols = StVKTets(X, tets, YOUNG, NU).rest_volume
    assert lumped_masses(X, tets, rho_e).sum().item() == pytest.approx((rho_e * vols).sum().item(), rel=1e-12)


# --------------------------------------------------------------------------- validation
def test_inverted_or_degenerate_rest_tet_raises():
    X, tets, _ = grid(2)
    bad = tets.clone()
    bad[7, 1], bad[7, 2] = tets[7, 2], tets[7, 1]
    with pytest.raises(ValueError, match=r"\b7\b"):
        StVKTets(X, bad, YOUNG, NU)
    flat = tets.clone()
    flat[11, 3] = flat[11, 2]  # repeated vertex: zero volume
    with pytest.raises(ValueError, match=r"\b11\b"):
        StVKTets(X, flat, YOUNG, NU)


def test_float32_states_round_trip():
    X, tets = random_tets(4, seed=16)
    term = StVKTets(X, tets, YOUNG, NU)
    xe = deform(term, X, random_F(4, 17, "generic"))
    g64, H64 = term.local_gradient_hessian(xe)
    g32, H32 = term.local_gradient_hessian(xe.float())
    assert g32.dtype == torch.float32 and H32.dtype == torch.float32
    assert rel(H32.double(), H64) < 1e-5
    assert term.local_energy(xe.float()).dtype == torch.float32

"""Discrete elastic rods (no twist): stretching and bending energies.

Physics checks: zero energy/force at rest, rigid-motion invariance, finite
differences, the compiled Hessians (``local_gradient_hessian``, the kernels of
``physics.kernels.rods``) against the autograd oracle (raw and projected),
batching, and analytic values (uniform stretch, circular arc).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from latentsim.physics.base import autograd_gradient_hessian, project_psd
from latentsim.physics.kernels.core import jacobi_eigh
from latentsim.physics.rods import (
    RodBend,
    RodStretch,
    lumped_masses_rods,
    rod_roots,
    rod_stiffness,
    rod_topology,
)


FLOAT64 = True  # tests/conftest.py: float64 default dtype for this module

Y, RADIUS, DENSITY = 2.0e9, 5.0e-5, 1300.0
KS, KB = rod_stiffness(Y, RADIUS)


def random_rotation(gen: torch.Generator) -> torch.Tensor:
    Q, R = torch.linalg.qr(torch.randn(3, 3, generator=gen))
    Q = Q * torch.sign(torch.diagonal(R))
    if torch.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def straight_rods(n_rods=3, m=8, seed=0):
    """Straight rods in random directions with non-uniform rest edge lengths."""
    gen = torch.Generator().manual_seed(seed)
    X = torch.zeros(n_rods * m, 3)
    for r in range(n_rods):
        d = torch.randn(3, generator=gen)
        d = d / d.norm()
        steps = 0.01 * (0.5 + torch.rand(m - 1, generator=gen))  # non-uniform spacing
        s = torch.cat([torch.zeros(1), torch.cumsum(steps, 0)])
        X[r * m : (r + 1) * m] = torch.randn(3, generator=gen) * 0.05 + s[:, None] * d
    edges, triples = rod_topology(n_rods, m)
    return X, edges, triples


@pytest.fixture(scope="module")
def rods():
    X, edges, triples = straight_rods()
    ks = KS * (1.0 + 0.1 * torch.arange(edges.shape[0]) / edges.shape[0])  # per-edge stiffness
    return X, RodStretch(X, edges, ks), RodBend(X, triples, KB)


def deformed(X, seed, scale=0.003):
    gen = torch.Generator().manual_seed(seed)
    return X + scale * torch.randn(X.shape, generator=gen)


# --------------------------------------------------------------------------
# parameters, topology, masses
# --------------------------------------------------------------------------
def test_stiffness_formulas():
    ks, kb = rod_stiffness(3.0e9, 2.0e-4)
    assert ks == pytest.approx(3.0e9 * math.pi * 4.0e-8, rel=1e-14)
    assert kb == pytest.approx(3.0e9 * math.pi * 1.6e-15 / 4.0, rel=1e-14)


def test_topology_contiguous_rods():
    edges, triples = rod_topology(3, 5)
    assert edges.shape == (12, 2) and triples.shape == (9, 3)
    assert edges.dtype == torch.long and triples.dtype == torch.long
    assert edges[:4].tolist() == [[0, 1], [1, 2], [2, 3], [3, 4]]
    assert edges[4].tolist() == [5, 6]  # no edge across rods
    assert triples[3].tolist() == [5, 6, 7]
    assert torch.all(triples[:, 1] - triples[:, 0] == 1) and torch.all(triples[:, 2] - triples[:, 1] == 1)
    assert not torch.any((edges // 5)[:, 0] != (edges // 5)[:, 1])
    assert rod_roots(3, 5).tolist() == [0, 5, 10]


def test_lumped_masses():
    X, edges, _ = straight_rods()
    m = lumped_masses_rods(X, edges, DENSITY, RADIUS)
    lengths = (X[edges[:, 1]] - X[edges[:, 0]]).norm(dim=-1)
    total = DENSITY * math.pi * RADIUS**2 * lengths.sum()
    assert m.sum().item() == pytest.approx(total.item(), rel=1e-13)
    # an interior vertex gets half of each adjacent edge, the tip half of one
    lin = DENSITY * math.pi * RADIUS**2
    assert m[3].item() == pytest.approx(0.5 * lin * (lengths[2] + lengths[3]).item(), rel=1e-13)
    assert m[7].item() == pytest.approx(0.5 * lin * lengths[6].item(), rel=1e-13)


# --------------------------------------------------------------------------
# rest state, invariances
# --------------------------------------------------------------------------
def test_zero_energy_and_force_at_rest(rods):
    X, stretch, bend = rods
    for term in (stretch, bend):
        e = term.element_energy(X)
        assert e.abs().max().item() < 1e-20
        g, H = term.local_gradient_hessian(term.gather(X))
        g_ad, H_ad = autograd_gradient_hessian(term, term.gather(X), project=True)
        assert g.abs().max().item() < 1e-9 * KS
        assert g_ad.abs().max().item() < 1e-9 * KS
        # at rest the Hessian is PSD already and equals the oracle
        assert torch.allclose(H, H_ad, rtol=1e-10, atol=1e-10 * H_ad.abs().max().item())


def test_bend_zero_for_stretched_straight_rod(rods):
    X, _, bend = rods
    # stretch every rod about its root: still straight, no bending energy
    x = X.clone()
    for r in range(3):
        sl = slice(8 * r, 8 * r + 8)
        x[sl] = X[sl][0] + 1.3 * (X[sl] - X[sl][0])
    assert bend.energy(x).item() < 1e-20


def test_rigid_motion_invariance(rods):
    X, stretch, bend = rods
    gen = torch.Generator().manual_seed(3)
    x = deformed(X, 1)
    Rm = random_rotation(gen)
    xr = x @ Rm.T + torch.randn(3, generator=gen)
    for term in (stretch, bend):
        e0, e1 = term.energy(x), term.energy(xr)
        assert e0.item() > 0
        assert e1.item() == pytest.approx(e0.item(), rel=1e-11)


# --------------------------------------------------------------------------
# derivatives
# --------------------------------------------------------------------------
def central_difference_gradient(term, x, h=1e-7):
    flat = x.reshape(-1)
    g = torch.zeros_like(flat)
    for i in range(flat.numel()):
        d = torch.zeros_like(flat)
        d[i] = h
        g[i] = (term.energy((flat + d).reshape(x.shape)) - term.energy((flat - d).reshape(x.shape))) / (2 * h)
    return g.reshape(x.shape)


def assemble_gradient(term, x, g_local):
    k = term.stencils.shape[1]
    g = torch.zeros_like(x)
    g.index_add_(0, term.stencils.reshape(-1), g_local.reshape(-1, k, 3).reshape(-1, 3))
    return g


@pytest.mark.parametrize("which", ["stretch", "bend"])
def test_gradient_finite_differences(rods, which):
    X, stretch, bend = rods
    term = stretch if which == "stretch" else bend
    for seed in (11, 12):
        x = deformed(X, seed)
        g_fd = central_difference_gradient(term, x)
        g_cf = assemble_gradient(term, x, term.local_gradient_hessian(term.gather(x))[0])
        scale = g_fd.abs().max().item()
        assert scale > 0
        assert (g_cf - g_fd).abs().max().item() < 1e-6 * scale


@pytest.mark.parametrize("which", ["stretch", "bend"])
@pytest.mark.parametrize("seed", [21, 22])
def test_hessian_matches_autograd_oracle(rods, which, seed):
    X, stretch, bend = rods
    term = stretch if which == "stretch" else bend
    # shrink towards the centroid so that some springs are compressed
    c = X.mean(0)
    x = deformed(c + 0.8 * (X - c), seed, scale=0.002 if seed == 21 else 0.004)
    xe = term.gather(x)
    for project in (False, True):
        g, H = term.local_gradient_hessian(xe, project=project)
        g0, H0 = autograd_gradient_hessian(term, xe, project=project)
        scale = H0.abs().amax((1, 2), keepdim=True)
        assert torch.allclose(g, g0, rtol=0, atol=1e-11 * g0.abs().max().item())
        assert ((H - H0).abs() / scale).max().item() < 1e-10
        assert torch.allclose(H, H.transpose(1, 2), rtol=0, atol=1e-13 * scale.max().item())
    # the raw Hessians are indefinite here; the projected ones are PSD
    H_raw = term.local_gradient_hessian(xe, project=False)[1]
    H_psd = term.local_gradient_hessian(xe, project=True)[1]
    w_raw = torch.linalg.eigvalsh(H_raw)
    w_psd = torch.linalg.eigvalsh(H_psd)
    assert (w_raw.min(-1).values < -1e-6 * w_raw.abs().max(-1).values).any()
    assert (w_psd.min(-1).values >= -1e-10 * w_psd.abs().max(-1).values).all()


def test_stretch_projection_clamps_compressed_springs(rods):
    X, stretch, _ = rods
    x = X.clone()
    x[1] = X[0] + 0.5 * (X[1] - X[0])  # edge 0 at half its rest length
    xe = stretch.gather(x)
    H_raw = stretch.local_gradient_hessian(xe, project=False)[1][0]
    H_psd = stretch.local_gradient_hessian(xe, project=True)[1][0]
    w = torch.linalg.eigvalsh(H_raw)
    # spring: eigenvalues 2 ks/L (along) and 2 ks/L (1 - L/l) = -2 ks/L (across, twice)
    s = 2.0 * stretch.ks[0] / stretch.rest_length[0]
    assert torch.allclose(w, torch.tensor([-s, -s, 0, 0, 0, s]), atol=1e-9 * s)
    assert torch.allclose(H_psd, project_psd(H_raw[None])[0], atol=1e-9 * s)


def test_bend_hessian_at_straight_and_nearly_straight_states(rods):
    """The stencil frame is degenerate for straight stencils: use the fallback."""
    X, _, bend = rods
    x_straight = X.clone()
    for r in range(3):
        sl = slice(8 * r, 8 * r + 8)
        x_straight[sl] = X[sl][0] + 1.1 * (X[sl] - X[sl][0])
    gen = torch.Generator().manual_seed(5)
    x_near = [x_straight + eps * torch.randn(X.shape, generator=gen) for eps in (1e-11, 1e-9, 1e-6)]
    for x in [x_straight] + x_near:
        xe = bend.gather(x)
        for project in (False, True):
            g, H = bend.local_gradient_hessian(xe, project=project)
            g0, H0 = autograd_gradient_hessian(bend, xe, project=project)
            assert torch.isfinite(H).all()
            scale = H0.abs().max().item()
            assert (H - H0).abs().max().item() < 1e-12 * scale
            # |g| ~ |H| |dx|: compare at the precision of the inputs (|x| ~ 0.1)
            assert (g - g0).abs().max().item() < 1e-14 * scale


@pytest.mark.parametrize("n", [3, 4, 9])
def test_jacobi_eigensolver(n):
    """The kernels' one small symmetric eigensolver (``kernels.core.jacobi_eigh``)."""
    rng = np.random.default_rng(n)
    A = rng.standard_normal((50, n, n))
    A = A + A.transpose(0, 2, 1)
    A[0] = 0.0  # zero matrix
    A[1] = np.diag(np.r_[np.ones(n - 1), 2.0])  # repeated eigenvalues
    A[2] = np.ones((n, n))  # rank one
    lam, V = np.empty((50, n)), np.empty((50, n, n))
    for e in range(50):
        jacobi_eigh(A[e].copy(), V[e], lam[e])
    assert np.allclose(np.einsum("eij,ejk->eik", V.transpose(0, 2, 1), V), np.eye(n), atol=1e-13)
    assert np.allclose((V * lam[:, None, :]) @ V.transpose(0, 2, 1), A, atol=1e-12)
    assert np.allclose(np.sort(lam, 1), np.linalg.eigvalsh(A), atol=1e-12)


# --------------------------------------------------------------------------
# batching
# --------------------------------------------------------------------------
def test_batched_energy_equals_separate_calls(rods):
    X, stretch, bend = rods
    xs = torch.stack([deformed(X, s) for s in range(4)])  # (B, n, 3)
    for term in (stretch, bend):
        batched = term.energy(xs)
        assert batched.shape == (4,)
        separate = torch.stack([term.energy(x) for x in xs])
        assert torch.allclose(batched, separate, rtol=1e-13, atol=0)
        # two leading axes
        assert torch.allclose(term.energy(xs.reshape(2, 2, *X.shape)).reshape(4), separate, rtol=1e-13, atol=0)


def test_float32_states(rods):
    X, stretch, bend = rods
    x = deformed(X, 2)
    for term in (stretch, bend):
        e32 = term.energy(x.float())
        assert e32.dtype == torch.float32
        assert e32.item() == pytest.approx(term.energy(x).item(), rel=1e-3)
        g, H = term.local_gradient_hessian(term.gather(x.float()))
        assert g.dtype == torch.float32 and H.dtype == torch.float32


# --------------------------------------------------------------------------
# analytic values
# --------------------------------------------------------------------------
def test_uniform_stretch_energy():
    L, m = 0.3, 12
    X = torch.zeros(m, 3)
    X[:, 1] = -torch.linspace(0, L, m)
    edges, triples = rod_topology(1, m)
    stretch, bend = RodStretch(X, edges, KS), RodBend(X, triples, KB)
    for s in (0.9, 1.02, 1.5):
        x = s * X
        assert stretch.energy(x).item() == pytest.approx(0.5 * KS * (s - 1) ** 2 * L, rel=1e-12)
        assert bend.energy(x).item() < 1e-25


def arc(L, R, m):
    """m vertices at equal arc spacing on a circle of radius R (arc length L)."""
    s = torch.linspace(0, L, m)
    return torch.stack([R * torch.sin(s / R), R * (1 - torch.cos(s / R)), torch.zeros(m)], -1)


def test_circular_arc_bending_energy():
    L, R = 0.2, 0.15
    errors = []
    for m in (11, 21, 41, 81):
        X = torch.zeros(m, 3)
        X[:, 0] = torch.linspace(0, L, m)
        _, triples = rod_topology(1, m)
        bend = RodBend(X, triples, KB)
        x = arc(L, R, m)
        e = bend.energy(x).item()
        # exact value of the discrete energy: chords c, turning angle phi = h/R
        h = L / (m - 1)
        c = 2 * R * math.sin(h / (2 * R))
        phi = h / R
        kappa = 2 * c * c * math.sin(phi) / (h * h + c * c * math.cos(phi))
        assert e == pytest.approx((m - 2) * KB * kappa**2 / (2 * h), rel=1e-12)
        errors.append(abs(e / (KB * L / (2 * R**2)) - 1.0))
    assert errors[-1] < 0.015
    assert all(b < 0.6 * a for a, b in zip(errors, errors[1:]))  # first-order convergence


def test_bending_energy_of_a_single_kink():
    """|kappa_b| = 2 tan(phi/2) at rest lengths: E = kb (2 tan(phi/2))^2 / (l0 + l1)."""
    l0, l1, phi = 0.01, 0.02, 0.7
    X = torch.tensor([[0.0, 0.0, 0.0], [l0, 0.0, 0.0], [l0 + l1, 0.0, 0.0]])
    bend = RodBend(X, torch.tensor([[0, 1, 2]]), KB)
    x = torch.tensor([[0.0, 0.0, 0.0], [l0, 0.0, 0.0], [l0 + l1 * math.cos(phi), l1 * math.sin(phi), 0.0]])
    assert bend.energy(x).item() == pytest.approx(KB * (2 * math.tan(phi / 2)) ** 2 / (l0 + l1), rel=1e-12)
    kb_vec = bend.curvature_binormal(bend.gather(x))[0]
    assert torch.allclose(kb_vec, torch.tensor([0.0, 0.0, 2 * math.tan(phi / 2)]), atol=1e-12)


# --------------------------------------------------------------------------
# input validation
# --------------------------------------------------------------------------
def test_rejects_curved_rest_shape():
    X = arc(0.1, 0.2, 6)
    _, triples = rod_topology(1, 6)
    with pytest.raises(ValueError, match="not straight"):
        RodBend(X, triples, KB)
    Xf = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0.0, 0, 0]])  # folded back
    with pytest.raises(ValueError, match="stencil 0"):
        RodBend(Xf, torch.tensor([[0, 1, 2]]), KB)


def test_rejects_zero_length_edges():
    X = torch.tensor([[0.0, 0, 0], [0.0, 0, 0], [1.0, 0, 0]])
    with pytest.raises(ValueError, match="zero"):
        RodStretch(X, torch.tensor([[0, 1], [1, 2]]), KS)
    with pytest.raises(ValueError, match="zero"):
        RodBend(X, torch.tensor([[0, 1, 2]]), KB)

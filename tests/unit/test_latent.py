"""Tests of the latent-space learning core (latentsim.latent).

The physical test system is a hanging chain of point masses joined by linear
springs, 1/2 k |x_i - x_j - (X_i - X_j)|^2, whose root (vertex 0, Dirichlet)
moves horizontally with a prescribed velocity p_t.  Its implicit-Euler step is
a linear solve, written out below independently of the energy code, which
gives a known answer for the self-supervised integrator.
"""

from __future__ import annotations

import copy
import math
import os

import numpy as np
import pytest
import torch

from latentsim.config import ConfigError
from latentsim.physics.base import EnergyTerm
from latentsim.physics.incremental_potential import IncrementalPotential
from latentsim.latent import (
    Autoencoder,
    LatentIntegrator,
    RelativeCoordinates,
    TrainingDiverged,
    balancing_weights,
    fixed_balancing_weights,
    build_triplets,
    decode_latents,
    encode_positions,
    fit_autoencoder,
    fit_integrator,
    integrator_loss,
    load_autoencoder,
    load_integrator,
    pca_basis,
    resolve_device,
    rollout,
    save_module,
)

F64 = torch.float64


ONE_THREAD = True  # tiny networks (conftest)


# ---------------------------------------------------------------------------
# the spring-chain system with a known implicit-Euler step
# ---------------------------------------------------------------------------
class LinearSpring(EnergyTerm):
    """1/2 k |x_i - x_j - (X_i - X_j)|^2 per edge (i, j)."""

    name = "linear_spring"

    def __init__(self, edges, X, k):
        self.stencils = torch.as_tensor(edges, dtype=torch.long)
        self.rest = X[self.stencils[:, 0]] - X[self.stencils[:, 1]]  # (E, 3)
        self.k = float(k)

    def local_energy(self, xe):
        d = xe[..., 0, :] - xe[..., 1, :] - self.rest.to(xe)
        return 0.5 * self.k * (d * d).sum(-1)


class Chain:
    def __init__(self, n=4, L=0.1, k=40.0, m=0.05, dt=1.0 / 30.0):
        self.n = n
        X = torch.zeros(n, 3, dtype=F64)
        X[:, 2] = -L * torch.arange(n, dtype=F64)
        self.X = X
        edges = [[i, i + 1] for i in range(n - 1)]
        self.pot = IncrementalPotential(
            terms=[LinearSpring(edges, X, k)],
            masses=torch.full((n,), m, dtype=F64),
            dt=dt,
            g=torch.tensor([0.0, 0.0, -9.81], dtype=F64),
            dirichlet=torch.tensor([0]),
            w_bc=1e5,
        )
        lap = torch.zeros(n, n, dtype=F64)
        for i, j in edges:
            lap[i, i] += 1
            lap[j, j] += 1
            lap[i, j] -= 1
            lap[j, i] -= 1
        self.K = k * torch.kron(lap, torch.eye(3, dtype=F64))  # spring energy = 1/2 (x-X)^T K (x-X)

    def exact_step(self, x1, x2, xD, h=None, stiffness=1.0):
        """Implicit Euler with the root held at xD (..., 1, 3): solve
        (M/h^2 + K)_ff x_f = M/h^2 (2 x1 - x2)_f + (M g)_f + (K X)_f - K_f0 x_0;
        at time step ``h`` (the potential's by default) with the springs ``stiffness`` times as stiff."""
        n, h = self.n, self.pot.dt if h is None else h
        lead = x1.shape[:-2]
        Mv = self.pot.masses.repeat_interleave(3)
        K = stiffness * self.K
        A = torch.diag(Mv) / h**2 + K
        y = (2 * x1 - x2).reshape(lead + (3 * n,))
        mg = (self.pot.masses[:, None] * self.pot.g).reshape(3 * n)
        xfix = torch.zeros(lead + (3 * n,), dtype=F64)
        xfix[..., :3] = xD.reshape(lead + (3,))
        rhs = Mv / h**2 * y + mg + K @ self.X.reshape(-1) - xfix @ K.T
        f = slice(3, 3 * n)
        xf = torch.linalg.solve(A[f, f], rhs[..., f].unsqueeze(-1)).squeeze(-1)
        out = xfix.clone()
        out[..., f] = xf
        return out.reshape(lead + (n, 3))

    def simulate(self, amp, freq, T=40):
        dt = self.pot.dt
        ts = torch.arange(T, dtype=F64) * dt
        vel = amp * torch.sin(2 * math.pi * freq * ts)  # p_t: root x-velocity
        rootx = torch.cumsum(vel * dt, 0) - vel[0] * dt
        xD = torch.zeros(T, 1, 3, dtype=F64)
        xD[:, 0, 0] = rootx
        xs = [self.X + xD[0], self.X + xD[1]]
        for t in range(2, T):
            xs.append(self.exact_step(xs[-1], xs[-2], xD[t]))
        return {"positions": torch.stack(xs), "dirichlet_positions": xD, "bc": vel[:, None]}


@pytest.fixture(scope="module")
def chain_setup():
    ch = Chain()
    seqs = [ch.simulate(a, f) for a, f in [(0.5, 1.0), (-0.8, 0.7), (1.0, 1.5)]]
    coords = RelativeCoordinates(ch.n, [0], "roots", root_of=[0] * ch.n)
    U = torch.cat([coords.encode(s["positions"], s["dirichlet_positions"]) for s in seqs])
    # latent_dim = d: an untrained PCA-initialised autoencoder is an exact linear bijection
    ae = Autoencoder(coords.dim, coords.dim, [16], pca_dim=coords.dim)
    ae.init_pca(U)
    ae.eval()
    return ch, seqs, coords, ae


INTEG_CFG = dict(widths=[64, 64], epochs=400, lr=3e-3, batch_size=32, noise_scale=0.1, balancing=True)


@pytest.fixture(scope="module")
def trained(chain_setup):
    ch, seqs, coords, ae = chain_setup
    integ, hist = fit_integrator(ae, coords, ch.pot, seqs, INTEG_CFG, seed=0)
    return integ, hist


def _one_step_error(integ, ch, ae, coords, seq):
    """Mean vertex error of the one-step prediction vs the exact implicit-Euler
    step (from ground-truth inputs), relative to the mean step displacement."""
    tr = build_triplets(ae, coords, [seq])
    with torch.no_grad():
        pred = integ(tr["z_prev"], tr["z_prev2"], tr["p"], tr["p_prev"], tr["p_prev2"])
        x = decode_latents(ae, coords, pred, tr["xD"])
        x1 = decode_latents(ae, coords, tr["z_prev"], tr["xD_prev"])
        x2 = decode_latents(ae, coords, tr["z_prev2"], tr["xD_prev2"])
    xe = ch.exact_step(x1, x2, tr["xD"])
    return float((x - xe).norm(dim=-1).mean() / (xe - x1).norm(dim=-1).mean())


def _untrained(chain_setup, widths=(64, 64), seed=1):
    ch, seqs, coords, ae = chain_setup
    tr = build_triplets(ae, coords, seqs)
    torch.manual_seed(seed)
    integ = LatentIntegrator(coords.dim, 1, widths)
    integ.fit_normalization(*(tr[k] for k in ("z", "z_prev", "z_prev2", "p", "p_prev", "p_prev2")))
    return integ.eval(), tr


# ---------------------------------------------------------------------------
# devices
# ---------------------------------------------------------------------------
def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="unknown device"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            resolve_device("cuda")


# ---------------------------------------------------------------------------
# relative coordinates
# ---------------------------------------------------------------------------
def test_relative_coordinates_roots_round_trip_and_roots_excluded():
    g = torch.Generator().manual_seed(0)
    n = 8  # two rods of 4 vertices, roots 0 and 4
    root_of = [0, 0, 0, 0, 4, 4, 4, 4]
    dirichlet = torch.tensor([0, 4])
    c = RelativeCoordinates(n, dirichlet, "roots", root_of=root_of)
    assert c.dim == 3 * 6 and c.hard_dirichlet
    assert set(c.encoded_vertices.tolist()) == {1, 2, 3, 5, 6, 7}
    x = torch.randn(5, 2, n, 3, generator=g, dtype=F64)  # batched leading axes
    xD = x[..., dirichlet, :].clone()
    u = c.encode(x, xD)
    assert u.shape == (5, 2, 18)
    # vertex 6 is stored relative to its root 4
    k = c.encoded_vertices.tolist().index(6)
    assert torch.equal(u.reshape(5, 2, 6, 3)[..., k, :], x[..., 6, :] - x[..., 4, :])
    assert torch.allclose(c.decode(u, xD), x, atol=1e-14, rtol=0)
    # roots are not in u: decoding any u re-applies the prescribed root positions
    xr = c.decode(torch.randn(18, generator=g, dtype=F64), xD[0, 0])
    assert torch.equal(xr[dirichlet], xD[0, 0])
    with pytest.raises(ValueError):
        RelativeCoordinates(n, dirichlet, "roots", root_of=[1] * n)  # root not Dirichlet


def test_relative_coordinates_mean_round_trip_and_translation_invariance():
    g = torch.Generator().manual_seed(1)
    n, dirichlet = 7, torch.tensor([0, 3])
    c = RelativeCoordinates(n, dirichlet, "mean")
    assert c.dim == 3 * n and not c.hard_dirichlet
    x = torch.randn(4, n, 3, generator=g, dtype=F64)
    xD = x[:, dirichlet, :] + 0.01  # prescribed positions need not equal x[D] in "mean" mode
    u = c.encode(x, xD)
    assert u.shape == (4, 3 * n)
    assert torch.allclose(u.reshape(4, n, 3), x - xD.mean(1, keepdim=True), atol=1e-15)
    assert torch.allclose(c.decode(u, xD), x, atol=1e-14, rtol=0)
    shift = torch.tensor([1.0, -2.0, 0.5], dtype=F64)
    assert torch.allclose(c.encode(x + shift, xD + shift), u, atol=1e-13)


def test_relative_coordinates_hard_mean_leaves_out_and_reapplies_the_prescribed_vertices():
    g = torch.Generator().manual_seed(2)
    n, dirichlet = 7, torch.tensor([0, 3, 5])
    c = RelativeCoordinates(n, dirichlet, "hard_mean")
    free = torch.tensor([1, 2, 4, 6])
    assert c.dim == 3 * 4 and c.hard_dirichlet and torch.equal(c.encoded_vertices, free)
    x = torch.randn(4, n, 3, generator=g, dtype=F64)
    xD = x[:, dirichlet, :]
    u = c.encode(x, xD)
    assert torch.allclose(u.reshape(4, 4, 3), x[:, free] - xD.mean(1, keepdim=True), atol=1e-15)
    assert torch.allclose(c.decode(u, xD), x, atol=1e-14, rtol=0)
    # any u: the prescribed vertices come back exactly at their targets
    y = c.decode(torch.randn(4, 12, generator=g, dtype=F64), xD + 0.3)
    assert torch.equal(y[:, dirichlet], xD + 0.3)
    shift = torch.tensor([1.0, -2.0, 0.5], dtype=F64)
    assert torch.allclose(c.encode(x + shift, xD + shift), u, atol=1e-13)
    with pytest.raises(ValueError, match="needs Dirichlet"):
        RelativeCoordinates(n, [], "hard_mean")


# ---------------------------------------------------------------------------
# autoencoder
# ---------------------------------------------------------------------------
def test_pca_initialised_autoencoder_reconstructs_linear_subspace():
    g = torch.Generator().manual_seed(2)
    d, N = 30, 64
    basis = torch.linalg.qr(torch.randn(d, 2, generator=g, dtype=F64))[0].T  # (2, d)
    coeff = torch.randn(N, 2, generator=g, dtype=F64) * torch.tensor([1.0, 0.3], dtype=F64)
    offset = torch.randn(d, generator=g, dtype=F64)
    U = coeff @ basis + offset  # exactly in a 2-D affine subspace
    torch.manual_seed(0)
    ae = Autoencoder(d, 2, widths=[16, 16], pca_dim=8).eval()
    with torch.no_grad():
        err_random = float((ae(U.float()).double() - U).pow(2).mean())
    ae.init_pca(U)
    with torch.no_grad():
        z = ae.encode(U.float())
        err_pca = float((ae.decode(z).double() - U).pow(2).mean())
    assert err_pca < 1e-10 and err_random > 1e-2
    assert err_pca < 1e-8 * err_random
    # the latents are the (scaled) principal coordinates: uncorrelated
    zc = (z - z.mean(0)).double()
    cov = zc.T @ zc / N
    assert abs(float(cov[0, 1])) < 1e-4 * float(cov[0, 0])
    # rank-deficient data (N - 1 < p): the basis is completed to p orthonormal rows
    _, V, std = pca_basis(U[:4], 8)
    assert V.shape == (8, d)
    assert torch.allclose(V @ V.T, torch.eye(8, dtype=F64), atol=1e-10)
    assert float(std[4:].abs().max()) < 1e-12


def _arc_family(N=128, n=10, L=1.0):
    """A chain of n points bent along a circular arc, total angle in [-2.5, 2.5]."""
    theta = torch.linspace(-2.5, 2.5, N, dtype=F64)
    s = torch.linspace(0, L, n, dtype=F64)
    ang = theta[:, None] * s[None, :] / L
    t = torch.stack([torch.cos(ang), torch.sin(ang), torch.zeros_like(ang)], -1)
    ds = L / (n - 1)
    x = torch.cumsum(t * ds, 1) - t[:, :1] * ds
    return x.reshape(N, -1)


def test_autoencoder_training_reduces_error_and_is_deterministic(tmp_path):
    U = _arc_family()
    cfg = dict(latent_dim=1, widths=[32, 32], epochs=100, lr=3e-3, batch_size=32)
    m1, h1 = fit_autoencoder(U, cfg, seed=0)
    m2, h2 = fit_autoencoder(U, cfg, seed=0)
    # a 1-D linear (PCA) subspace cannot hold the arc family; the network can
    assert h1["mse_final"] < h1["mse_initial"] / 5
    assert h1["loss"][-1] < h1["loss"][0]
    s1, s2 = m1.state_dict(), m2.state_dict()
    assert s1.keys() == s2.keys() and all(torch.equal(s1[k], s2[k]) for k in s1)
    assert h1["loss"] == h2["loss"]
    # round trip through disk (weights_only loading)
    save_module(tmp_path / "ae.pt", m1)
    m3 = load_autoencoder(tmp_path / "ae.pt")
    with torch.no_grad():
        assert torch.equal(m3(U.float()), m1(U.float()))


# ---------------------------------------------------------------------------
# losses
# ---------------------------------------------------------------------------
def test_self_supervised_loss_is_the_incremental_potential(chain_setup):
    ch, seqs, coords, ae = chain_setup
    integ, tr = _untrained(chain_setup)
    batch = {k: v[:10] for k, v in tr.items()}
    loss, info = integrator_loss(integ, ae, coords, ch.pot, batch, noise_scale=0.0, balancing=False)
    with torch.no_grad():
        pred = integ(batch["z_prev"], batch["z_prev2"], batch["p"], batch["p_prev"], batch["p_prev2"])
        x = decode_latents(ae, coords, pred, batch["xD"])
        x1 = decode_latents(ae, coords, batch["z_prev"], batch["xD_prev"])
        x2 = decode_latents(ae, coords, batch["z_prev2"], batch["xD_prev2"])
    assert x.dtype == F64
    e = ch.pot(x, x1, x2, targets=batch["xD"], penalty=False)
    assert info["count"] == 10
    assert torch.allclose(info["per_sample"], e, rtol=1e-12, atol=1e-12)
    assert torch.allclose(loss, e.mean(), rtol=1e-12)
    # the loss is differentiable w.r.t. the integrator weights
    loss.backward()
    assert all(p.grad is not None for p in integ.parameters())
    # balanced: each sample divided by |mean velocity of the previous step|
    loss_b, info_b = integrator_loss(integ, ae, coords, ch.pot, batch, noise_scale=0.0, balancing=True)
    v = ((x1 - x2) / ch.pot.dt).mean(-2).norm(dim=-1)
    assert torch.allclose(loss_b, (e / v.clamp_min(1e-2)).mean(), rtol=1e-10)
    # "mean" coordinates switch the Dirichlet penalty on automatically
    cm = RelativeCoordinates(ch.n, [0], "mean")
    assert not cm.hard_dirichlet
    Um = torch.cat([cm.encode(s["positions"], s["dirichlet_positions"]) for s in seqs])
    aem = Autoencoder(cm.dim, cm.dim, [8], pca_dim=cm.dim).eval()
    aem.init_pca(Um)
    zm = {k: encode_positions(aem, cm, seqs[0]["positions"][o : o + 10], seqs[0]["dirichlet_positions"][o : o + 10])
          for k, o in (("z", 2), ("z_prev", 1), ("z_prev2", 0))}
    bm = {**batch, **zm, "xD": batch["xD"] + 0.01}  # targets off the decoded root: penalty > 0
    im = LatentIntegrator(cm.dim, 1, [8]).eval()
    loss_m, info_m = integrator_loss(im, aem, cm, ch.pot, bm, noise_scale=0.0, balancing=False)
    with torch.no_grad():
        xm = decode_latents(aem, cm, im(bm["z_prev"], bm["z_prev2"], bm["p"], bm["p_prev"], bm["p_prev2"]), bm["xD"])
        xm1 = decode_latents(aem, cm, bm["z_prev"], bm["xD_prev"])
        xm2 = decode_latents(aem, cm, bm["z_prev2"], bm["xD_prev2"])
    e_pen = ch.pot(xm, xm1, xm2, targets=bm["xD"], penalty=True)
    e_nopen = ch.pot(xm, xm1, xm2, targets=bm["xD"], penalty=False)
    assert torch.allclose(info_m["per_sample"], e_pen, rtol=1e-12) and (e_pen > e_nopen + 1.0).all()
    # supervised variant: squared L2 to the ground-truth latent
    loss_s, _ = integrator_loss(integ, ae, coords, ch.pot, batch, mode="supervised", noise_scale=0.0, balancing=False)
    assert torch.allclose(loss_s, ((pred - batch["z"]) ** 2).sum(-1).double().mean(), rtol=1e-6)


def test_balancing_weights_computed_once_are_each_minibatchs(chain_setup):
    """The supervised baselines' weights (no noise, fixed triplets) computed once over the set equal those the
    loss computes from each shuffled minibatch's decodes (to float32 rounding: a GEMM of a handful of rows may
    take another path than one of hundreds; from about ten rows on they agree to the bit on the machines tried),
    and the loss is the weighted mean with them; with training noise they are refused."""
    ch, _, coords, ae = chain_setup
    integ, tr = _untrained(chain_setup)
    fixed = fixed_balancing_weights(ae, coords, tr, float(ch.pot.dt), 1e-2)
    assert fixed.shape == (tr["z"].shape[0],)
    rows = torch.randperm(tr["z"].shape[0], generator=torch.Generator().manual_seed(0))[:32]
    batch = {k: v[rows] for k, v in tr.items()}
    loss, info = integrator_loss(integ, ae, coords, ch.pot, batch, mode="supervised", noise_scale=0.0, balancing=True)
    loss_f, info_f = integrator_loss(integ, ae, coords, ch.pot, dict(batch, balance=fixed[rows]), mode="supervised", noise_scale=0.0, balancing=True)
    assert torch.allclose(info_f["weights"], info["weights"], rtol=1e-6, atol=0) and torch.allclose(loss_f, loss, rtol=1e-6, atol=0)
    assert torch.equal(info_f["weights"], fixed[rows]) and torch.equal(loss_f, (fixed[rows] * info_f["per_sample"]).mean())
    assert float(info["weights"].max() / info["weights"].min()) > 1.5  # the weights are not all alike
    with pytest.raises(ValueError, match="do not hold for inputs with training noise"):
        integrator_loss(integ, ae, coords, ch.pot, dict(batch, balance=fixed[rows]), mode="supervised", noise_scale=0.1, balancing=True)


def test_training_noise_doubles_batch_and_perturbs_only_latents(chain_setup):
    ch, seqs, coords, ae = chain_setup
    _, tr = _untrained(chain_setup)
    B = 16
    batch = {k: v[:B] for k, v in tr.items()}
    seen = {}

    def recorder(z1, z2, p, p1, p2):  # any callable can stand in for the integrator
        seen.update(z1=z1, z2=z2, p=p, p1=p1, p2=p2)
        return z1 + 0.0 * z1.sum()

    g = torch.Generator().manual_seed(0)
    _, info = integrator_loss(recorder, ae, coords, ch.pot, batch, noise_scale=0.1, balancing=True, generator=g)
    assert info["count"] == 2 * B and info["per_sample"].shape == (2 * B,)
    assert torch.equal(seen["z1"][:B], batch["z_prev"]) and torch.equal(seen["z2"][:B], batch["z_prev2"])
    for key, src in (("z1", "z_prev"), ("z2", "z_prev2")):
        delta = seen[key][B:] - batch[src]
        amp = 0.1 * batch[src].std(0, unbiased=False)
        assert (delta.abs() <= amp + 1e-7).all() and delta.abs().max() > 0.5 * amp.max()
    for key, src in (("p", "p"), ("p1", "p_prev"), ("p2", "p_prev2")):
        assert torch.equal(seen[key][B:], batch[src])  # BCs unchanged
    _, info0 = integrator_loss(recorder, ae, coords, ch.pot, batch, noise_scale=0.0, balancing=True)
    assert info0["count"] == B


def test_supervised_weight_adds_the_l2_term_on_the_clean_samples(chain_setup):
    ch, seqs, coords, ae = chain_setup
    integ, tr = _untrained(chain_setup)
    B = 12
    batch = {k: v[:B] for k, v in tr.items()}
    kw = dict(noise_scale=0.1, balancing=True)
    l0, info = integrator_loss(integ, ae, coords, ch.pot, batch, generator=torch.Generator().manual_seed(3), **kw)
    lw, _ = integrator_loss(integ, ae, coords, ch.pot, batch, generator=torch.Generator().manual_seed(3), supervised_weight=0.5, **kw)
    pred = info["prediction"][:B]  # the unperturbed half
    sup = (((pred - batch["z"]) / integ.out_std) ** 2).sum(-1).mean()
    assert torch.allclose(lw - l0, 0.5 * sup.double(), rtol=1e-6)
    with pytest.raises(ValueError, match="supervised_weight"):
        integrator_loss(integ, ae, coords, ch.pot, batch, mode="supervised", supervised_weight=0.5)
    with pytest.raises(ValueError, match="supervised_weight"):
        integrator_loss(integ, ae, coords, ch.pot, batch, supervised_weight=-1.0)


def test_supervised_weight_pulls_a_lossy_latent_space_towards_the_data(chain_setup):
    """In a latent space smaller than the chain's (2 of 9 dimensions) the incremental potential's
    minimiser is not the ground truth's projection: the self-supervised integrator settles away
    from the ground-truth latents, and the supervision term pulls it most of the way back."""
    ch, seqs, _, _ = chain_setup
    coords = RelativeCoordinates(ch.n, [0], "roots", root_of=[0] * ch.n)
    U = torch.cat([coords.encode(s["positions"], s["dirichlet_positions"]) for s in seqs])
    ae = Autoencoder(coords.dim, 2, [16], pca_dim=coords.dim)
    ae.init_pca(U)
    ae.eval()
    cfg = dict(INTEG_CFG, epochs=150)
    _, plain = fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=0)
    _, mixed = fit_integrator(ae, coords, ch.pot, seqs, {**cfg, "supervised_weight": 1.0}, seed=0)
    # 9.6e-6 against 2.1e-5 (with weights 10 and 100 also 9.8e-6: the network's own floor)
    assert mixed["latent_mse"][-1] < 0.6 * plain["latent_mse"][-1], (mixed["latent_mse"][-1], plain["latent_mse"][-1])


def test_balancing_weights_hand_made():
    dt = 0.1
    x2 = torch.zeros(3, 5, 3, dtype=F64)
    x1 = x2.clone()
    x1[0] += torch.tensor([0.3, 0.4, 0.0], dtype=F64) * dt  # rigid motion, |v| = 0.5
    x1[1, 0, 0] = 1.0 * dt  # one vertex moves: mean velocity (0.2, 0, 0)
    x1[1, 1, 0] = 1.0 * dt
    # x1[2] at rest: |v| = 0 -> weight capped at 1/eps
    w = balancing_weights(x1, x2, dt, eps=1e-2)
    assert torch.allclose(w, torch.tensor([2.0, 1.0 / 0.4, 100.0], dtype=F64))


# ---------------------------------------------------------------------------
# integrator training against a known answer
# ---------------------------------------------------------------------------
def test_self_supervised_integrator_learns_implicit_euler(chain_setup, trained):
    ch, seqs, coords, ae = chain_setup
    integ, hist = trained
    untrained, _ = _untrained(chain_setup)
    unseen = ch.simulate(0.7, 1.2)  # a BC trajectory not in the training set
    err_train = _one_step_error(integ, ch, ae, coords, seqs[0])
    err_test = _one_step_error(integ, ch, ae, coords, unseen)
    err_untrained = _one_step_error(untrained, ch, ae, coords, seqs[0])
    assert err_train < 0.08 and err_test < 0.12, (err_train, err_test)
    assert err_train < 0.2 * err_untrained, (err_train, err_untrained)
    assert len(hist["loss"]) == INTEG_CFG["epochs"] and hist["n_triplets"] == 3 * 38
    assert hist["latent_mse"][-1] < 0.1 * hist["latent_mse"][0]


def test_checkpoint_resume_equals_uninterrupted(chain_setup, tmp_path):
    ch, seqs, coords, ae = chain_setup
    cfg = dict(widths=[16], epochs=6, lr=1e-3, batch_size=40)
    full, hf = fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=3)
    path = tmp_path / "ckpt.pt"
    fit_integrator(ae, coords, ch.pot, seqs, {**cfg, "epochs": 3}, seed=3, checkpoint_path=path, checkpoint_every=1)
    state = torch.load(path, weights_only=True)
    assert state["epoch"] == 3 and "optimizer" in state and len(state["optimizer"]["state"]) > 0
    resumed, hr = fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=3, checkpoint_path=path, checkpoint_every=1)
    assert hr["start_epoch"] == 3 and len(hr["loss"]) == 6
    assert hr["loss"] == hf["loss"]
    sf, sr = full.state_dict(), resumed.state_dict()
    assert all(torch.equal(sf[k], sr[k]) for k in sf)
    assert torch.load(path, weights_only=True)["epoch"] == 6
    save_module(tmp_path / "integ.pt", resumed)
    again = load_integrator(tmp_path / "integ.pt")
    assert all(torch.equal(again.state_dict()[k], sr[k]) for k in sr)



@pytest.mark.parametrize(
    "change",
    ["widths", "lr", "noise", "seed", "data", "fewer_epochs"],
)
def test_a_checkpoint_of_another_training_is_not_resumed(chain_setup, tmp_path, change, caplog):
    """After a config edit (or new data) the pipeline reruns the training with the old checkpoint on
    disk: it must start over, giving exactly a fresh run's result, never continue the old weights."""
    ch, seqs, coords, ae = chain_setup
    cfg = dict(widths=[16], epochs=4, lr=1e-3, batch_size=40)
    path = tmp_path / "ckpt.pt"
    fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=3, checkpoint_path=path, checkpoint_every=1)
    new_cfg, new_seed, new_seqs = dict(cfg), 3, seqs
    if change == "widths":
        new_cfg["widths"] = [8]
    elif change == "lr":
        new_cfg["lr"] = 3e-3
    elif change == "noise":
        new_cfg["noise_scale"] = 0.0
    elif change == "seed":
        new_seed = 4
    elif change == "data":
        new_seqs = seqs[:2]
    else:
        new_cfg["epochs"] = 2
    fresh, hf = fit_integrator(ae, coords, ch.pot, new_seqs, new_cfg, seed=new_seed)
    with caplog.at_level("WARNING", logger="latentsim.latent"):
        again, ha = fit_integrator(ae, coords, ch.pot, new_seqs, new_cfg, seed=new_seed, checkpoint_path=path, checkpoint_every=1)
    assert "starting over" in caplog.text
    assert ha["start_epoch"] == 0 and ha["loss"] == hf["loss"]
    assert all(torch.equal(a, b) for a, b in zip(fresh.state_dict().values(), again.state_dict().values()))
    assert torch.load(path, weights_only=True)["epoch"] == new_cfg["epochs"]  # overwritten by the new training


def test_cosine_learning_rate_decay(chain_setup, tmp_path):
    """lr_final: the rate follows lr_final + (lr - lr_final)(1 + cos(pi e / E)) / 2 over the epochs
    (a function of the epoch, so a resumed run sets it alike); lr_final = lr is the constant run."""
    ch, seqs, coords, ae = chain_setup
    cfg = dict(widths=[16], epochs=5, lr=1e-3, batch_size=40)
    path = tmp_path / "cos.pt"
    fit_integrator(ae, coords, ch.pot, seqs, {**cfg, "lr_final": 1e-5}, seed=3, checkpoint_path=path, checkpoint_every=1)
    last = torch.load(path, weights_only=True)["optimizer"]["param_groups"][0]["lr"]
    assert last == pytest.approx(1e-5 + 0.5 * (1e-3 - 1e-5) * (1 + math.cos(math.pi * 4 / 5)), rel=1e-12)
    const, hc = fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=3)
    flat, hf = fit_integrator(ae, coords, ch.pot, seqs, {**cfg, "lr_final": 1e-3}, seed=3)
    assert hf["loss"] == hc["loss"]
    decayed, hd = fit_integrator(ae, coords, ch.pot, seqs, {**cfg, "lr_final": 1e-5}, seed=3)
    assert hd["loss"][0] == hc["loss"][0] and hd["loss"][-1] != hc["loss"][-1]  # same first epoch, then slower steps


class _NaNAfter:
    """Wraps a potential; returns NaN from the (calls+1)-th evaluation on."""

    def __init__(self, pot, calls):
        self.pot, self.calls, self.n = pot, calls, 0

    def __getattr__(self, name):
        return getattr(self.pot, name)

    def __call__(self, *a, **k):
        self.n += 1
        e = self.pot(*a, **k)
        return e * float("nan") if self.n > self.calls else e


def test_nan_raises_training_diverged_and_keeps_checkpoint(chain_setup, tmp_path):
    ch, seqs, coords, ae = chain_setup
    cfg = dict(widths=[16], epochs=5, lr=1e-3, batch_size=40)  # 114 triplets -> 3 batches
    path = tmp_path / "ckpt.pt"
    with pytest.raises(TrainingDiverged, match="epoch 3") as exc:
        fit_integrator(ae, coords, _NaNAfter(ch.pot, calls=2 * 3 + 1), seqs, cfg, seed=0, checkpoint_path=path, checkpoint_every=1)
    assert exc.value.epoch == 3 and exc.value.batch == 1
    assert not os.path.exists(str(path) + ".tmp")
    state = torch.load(path, weights_only=True)
    assert state["epoch"] == 2 and all(torch.isfinite(v).all() for v in state["model"].values())
    # resuming with a sane potential continues from epoch 2
    _, hist = fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=0, checkpoint_path=path, checkpoint_every=1)
    assert hist["start_epoch"] == 2 and len(hist["loss"]) == 5


# ---------------------------------------------------------------------------
# training health: a training that blows up without a NaN stops, by name
# ---------------------------------------------------------------------------
HEALTH_CFG = dict(widths=[16], epochs=5, lr=1e-3, batch_size=40)  # 114 triplets -> 3 batches


def test_a_blown_up_training_stops_in_its_first_epoch_naming_label_epoch_and_loss(chain_setup, tmp_path):
    """Learning rate 1e3: the loss is 1e14 after the first epoch, finite; the integrator used to be
    written as complete.  Now TrainingDiverged names what trained, the epoch, the loss and the bound,
    and no checkpoint is written for the diverged epoch."""
    ch, seqs, coords, ae = chain_setup
    path = tmp_path / "ckpt.pt"
    with pytest.raises(TrainingDiverged) as exc:
        fit_integrator(ae, coords, ch.pot, seqs, {**HEALTH_CFG, "lr": 1e3}, seed=0, checkpoint_path=path, checkpoint_every=1, label="scene chain, method self_supervised")
    e = exc.value
    assert e.epoch == 1 and e.label == "scene chain, method self_supervised" and math.isfinite(e.value) and e.value > 1e3
    message = str(e)
    assert message.startswith("scene chain, method self_supervised: training diverged in epoch 1: loss ")
    assert f"{e.value:.4g}" in message and "far above its start" in message and "integrator.divergence_factor = 100" in message
    assert not path.exists() and not os.path.exists(str(path) + ".tmp")


def test_a_ramped_learning_rate_diverges_later_and_the_last_good_checkpoint_stays(chain_setup, tmp_path):
    """The learning rate ramped (cosine) from 1e-3 up to 10: healthy for some epochs, then far above
    the start.  The checkpoint on disk is the epoch before, with finite weights and losses within the
    bound; the history it holds starts from the same first-minibatch loss as a healthy run's."""
    ch, seqs, coords, ae = chain_setup
    cfg = {**HEALTH_CFG, "epochs": 30, "lr_final": 10.0}
    path = tmp_path / "ckpt.pt"
    with pytest.raises(TrainingDiverged, match=r"training diverged in epoch \d+: loss .* far above its start") as exc:
        fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=0, checkpoint_path=path, checkpoint_every=1)
    k = exc.value.epoch
    assert 2 < k < 30
    state = torch.load(path, weights_only=True)
    assert state["epoch"] == k - 1 and all(torch.isfinite(v).all() for v in state["model"].values())
    h = state["history"]
    bound = h["loss_start"] + 100 * h["loss_scale"]
    assert len(h["loss"]) == k - 1 and max(h["loss"]) <= bound < exc.value.value
    _, healthy = fit_integrator(ae, coords, ch.pot, seqs, HEALTH_CFG, seed=0)
    assert healthy["loss_start"] == h["loss_start"] and healthy["loss_scale"] == h["loss_scale"]
    assert max(healthy["loss"]) <= healthy["loss_start"] + 0.5 * healthy["loss_scale"]  # far inside the bound


def test_a_configured_loss_bound_stops_the_training(chain_setup):
    ch, seqs, coords, ae = chain_setup
    _, healthy = fit_integrator(ae, coords, ch.pot, seqs, HEALTH_CFG, seed=0)
    bound = min(healthy["loss"]) - abs(min(healthy["loss"])) - 1.0  # below every epoch's loss
    with pytest.raises(TrainingDiverged, match=r"^chain: training diverged in epoch 1: loss \S+ above integrator.max_loss = ") as exc:
        fit_integrator(ae, coords, ch.pot, seqs, {**HEALTH_CFG, "max_loss": bound}, seed=0, label="chain")
    assert exc.value.value == healthy["loss"][0]


def test_latents_leaving_the_training_range_stop_the_training(chain_setup):
    """One-step predictions from ground-truth inputs stay within about the radius R of the training
    latents (the healthy run: at most 1.1 R); a blow-up whose loss rule is switched off is caught
    by the latent range alone, and a factor below 1 trips even on a healthy training."""
    ch, seqs, coords, ae = chain_setup
    _, healthy = fit_integrator(ae, coords, ch.pot, seqs, HEALTH_CFG, seed=0)
    assert 0.5 * healthy["latent_radius"] < max(healthy["latent_distance"]) < 2 * healthy["latent_radius"]
    with pytest.raises(TrainingDiverged, match=r"epoch 1: the predicted latents leave the training range: .* times their radius") as exc:
        fit_integrator(ae, coords, ch.pot, seqs, {**HEALTH_CFG, "lr": 1e3, "divergence_factor": 1e30}, seed=0)
    assert exc.value.value > 10 * healthy["latent_radius"]
    with pytest.raises(TrainingDiverged, match=r"latent_range_factor = 0.5"):
        fit_integrator(ae, coords, ch.pot, seqs, {**HEALTH_CFG, "latent_range_factor": 0.5}, seed=0)


class _Killed(Exception):
    pass


class _Clock:
    """Wraps a potential: every evaluation (one per minibatch) advances a clock by one second, and
    the evaluation after ``kill_after`` raises (a kill -9 mid-epoch)."""

    def __init__(self, pot, start=0.0, kill_after=None):
        self.pot, self.now, self.kill_after, self.calls = pot, float(start), kill_after, 0

    def __getattr__(self, name):
        return getattr(self.pot, name)

    def __call__(self, *a, **k):
        self.calls += 1
        if self.kill_after is not None and self.calls > self.kill_after:
            raise _Killed
        self.now += 1.0
        return self.pot(*a, **k)


def test_a_resumed_training_records_the_sum_of_its_parts(chain_setup, tmp_path, monkeypatch):
    """On a clock that ticks once per minibatch (3 per epoch): the uninterrupted 6 epochs take 18 s;
    a run killed in epoch 5 leaves the checkpoint of epoch 4 with its 12 s, and the resumed run adds
    its own 6 s: 18 s, with the uninterrupted run's weights (the killed run's lost part, after
    its checkpoint, is redone and counted once)."""
    from types import SimpleNamespace

    from latentsim.latent import training

    ch, seqs, coords, ae = chain_setup
    cfg = {**HEALTH_CFG, "epochs": 6}

    def run(clock, path=None):
        monkeypatch.setattr(training, "time", SimpleNamespace(perf_counter=lambda: clock.now))
        return fit_integrator(ae, coords, clock, seqs, cfg, seed=3, checkpoint_path=path, checkpoint_every=2)

    full, hf = run(_Clock(ch.pot, start=100.0))
    assert hf["train_seconds"] == 18.0
    path = tmp_path / "ckpt.pt"
    with pytest.raises(_Killed):
        run(_Clock(ch.pot, kill_after=13), path)
    state = torch.load(path, weights_only=True)
    assert state["epoch"] == 4 and state["train_seconds"] == 12.0
    resumed, hr = run(_Clock(ch.pot, start=5000.0), path)
    assert hr["start_epoch"] == 4 and hr["train_seconds"] == 18.0
    assert hr["loss"] == hf["loss"] and all(torch.equal(a, b) for a, b in zip(full.state_dict().values(), resumed.state_dict().values()))


def test_a_blown_up_autoencoder_training_stops_naming_label_epoch_and_loss():
    U = torch.as_tensor(_arc_family(), dtype=torch.float32)
    cfg = dict(latent_dim=2, widths=[16], epochs=4, batch_size=32)
    _, healthy = fit_autoencoder(U, {**cfg, "lr": 1e-3}, seed=0)
    assert max(healthy["loss"]) < healthy["loss_start"] + 1.0  # within the bound (the scale's floor 0.01 x 100)
    with pytest.raises(TrainingDiverged, match=r"^scene arc: training diverged in epoch 1: loss \S+ far above its start .*autoencoder.divergence_factor") as exc:
        fit_autoencoder(U, {**cfg, "lr": 1e3}, seed=0, label="scene arc")
    assert exc.value.value > 1.0
    with pytest.raises(TrainingDiverged, match=r"above autoencoder.max_loss = 1e-12"):
        fit_autoencoder(U, {**cfg, "lr": 1e-3, "max_loss": 1e-12}, seed=0)


# ---------------------------------------------------------------------------
# rollout
# ---------------------------------------------------------------------------
class _Scaling(torch.nn.Module):
    """Scales the relative coordinates by ``factor`` every step."""

    def __init__(self, ae, factor):
        super().__init__()
        self.ae, self.factor = ae, factor

    def forward(self, z1, z2, p, p1, p2):
        return self.ae.encode(self.factor * self.ae.decode(z1))


def test_rollout_divergence_detection(chain_setup, trained):
    ch, seqs, coords, ae = chain_setup
    seq = seqs[1]
    T = seq["positions"].shape[0]
    z = encode_positions(ae, coords, seq["positions"], seq["dirichlet_positions"])
    args = (z[0], z[1], seq["bc"], seq["dirichlet_positions"])

    # the integrator sees z_{t-1}, z_{t-2} and exactly p_t, p_{t-1}, p_{t-2}
    calls = []

    def recorder(z1, z2, p, p1, p2):
        calls.append((z1.clone(), z2.clone(), float(p), float(p1), float(p2)))
        return z1 + 1.0

    out = rollout(recorder, ae, coords, z[0], z[1], torch.arange(T, dtype=F64)[:, None], seq["dirichlet_positions"])
    assert [c[2:] for c in calls] == [(t, t - 1, t - 2) for t in range(2, T)]
    assert torch.equal(calls[0][0][0], z[1]) and torch.equal(calls[0][1][0], z[0])
    assert torch.equal(calls[5][0][0], out["latents"][6]) and torch.equal(calls[5][1][0], out["latents"][5])
    assert torch.allclose(out["latents"][T - 1], z[1] + (T - 2), atol=1e-4)
    # a correction (the contact projection fed back) is applied to the start and each prediction, and is what
    # the next step is given: here halving every latent
    seen, calls = [], []
    halved = rollout(recorder, ae, coords, z[0], z[1], torch.arange(T, dtype=F64)[:, None], seq["dirichlet_positions"],
                     correct=lambda t, zt: (seen.append(t), 0.5 * zt)[1])  # fmt: skip
    assert seen == list(range(T))
    assert torch.allclose(calls[0][0][0], 0.5 * z[1]) and torch.allclose(calls[0][1][0], 0.5 * z[0])
    assert torch.equal(calls[5][0][0], halved["latents"][6]) and torch.allclose(halved["latents"][7], 0.5 * (halved["latents"][6] + 1.0))

    # relative coordinates x10 per step: extent / rest extent = 10^(t-1) -> exceeds 50 first at t = 3
    out = rollout(_Scaling(ae, 10.0), ae, coords, *args, max_extent=50.0, rest_positions=ch.X)
    assert out["diverged_frame"] == 3
    assert torch.isfinite(out["positions"][:4]).all() and torch.isnan(out["positions"][4:]).all()
    assert torch.isnan(out["latents"][4:]).all() and out["positions"].shape == (T, ch.n, 3)
    # overflow to inf/NaN without an extent limit: detected, not raised
    out = rollout(_Scaling(ae, 1e30), ae, coords, *args)
    assert out["diverged_frame"] == 3 and torch.isnan(out["positions"][4:]).all()

    # a real integrator with weights blown up diverges ...
    torch.manual_seed(0)  # independent of what earlier tests drew
    integ = LatentIntegrator(coords.dim, 1, [32, 32])
    with torch.no_grad():
        for prm in integ.mlp.parameters():
            prm.mul_(30.0)
    out = rollout(integ, ae, coords, *args, max_extent=10.0)
    assert out["diverged_frame"] >= 2
    # ... one that keeps z_{t-1} is stable
    with torch.no_grad():
        integ.mlp[-1].weight.zero_()
        integ.mlp[-1].bias.zero_()
    out = rollout(integ, ae, coords, *args, max_extent=10.0, potential=ch.pot)
    assert out["diverged_frame"] == -1 and torch.isfinite(out["positions"]).all()
    assert out["kinetic_energy"].shape == (T,) and torch.isnan(out["kinetic_energy"][0])

    # the trained self-supervised integrator rolls out stably and close to the reference
    integ, _ = trained
    out = rollout(integ, ae, coords, *args, max_extent=10.0, potential=ch.pot, rest_positions=ch.X)
    assert out["diverged_frame"] == -1
    ref = seq["positions"]
    err = (out["positions"] - ref).norm(dim=-1).mean()
    motion = (ref - ref[0]).norm(dim=-1).mean()
    assert float(err) < 0.2 * float(motion), (float(err), float(motion))
    # Dirichlet roots are exact in "roots" coordinates
    assert torch.allclose(out["positions"][:, 0], seq["dirichlet_positions"][:, 0], atol=1e-12)


def test_autoencoder_never_returns_worse_than_its_pca_start():
    """On data in an exact 3D subspace, PCA is exact; SGD can only make it worse, so the PCA start is kept."""
    gen = torch.Generator().manual_seed(0)
    U = torch.randn(200, 3, generator=gen) @ torch.randn(3, 30, generator=gen)
    model, hist = fit_autoencoder(U, {"latent_dim": 3, "widths": [16, 16], "epochs": 30, "lr": 0.1, "batch_size": 50}, seed=0)
    assert hist["kept"] == "pca"
    assert hist["mse_final"] == hist["mse_initial"] < 1e-10
    with torch.no_grad():
        assert ((model(U) - U) ** 2).mean() < 1e-10


def test_settings_come_from_the_schema():
    """Partial settings take the config schema's defaults (pca_dim 0: the first width, capped at the
    data dimension); a key the schema does not know stops the training, naming it."""
    U = torch.randn(40, 12, generator=torch.Generator().manual_seed(0))
    model, hist = fit_autoencoder(U, {"latent_dim": 2, "widths": [8], "epochs": 1, "batch_size": 16}, seed=0)
    assert model.pca_dim == 8 and hist["epochs"] == 1
    model, _ = fit_autoencoder(U, {"latent_dim": 2, "widths": [16], "epochs": 1, "batch_size": 16}, seed=0)
    assert model.pca_dim == 12
    with pytest.raises(ConfigError, match="fit_autoencoder.*'lr_decay'"):
        fit_autoencoder(U, {"lr_decay": 0.5})
    with pytest.raises(ConfigError, match="fit_integrator.*'checkpoint_every'"):
        fit_integrator(model, RelativeCoordinates(4, [0]), None, [], {"checkpoint_every": 1})


# ---------------------------------------------------------------------------
# the origin input: where the body is in the world
# ---------------------------------------------------------------------------
def _rotation(axis, angle) -> torch.Tensor:
    """The rotation by ``angle`` about ``axis`` (Rodrigues), float64."""
    k = torch.as_tensor(axis, dtype=F64)
    k = k / k.norm()
    K = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=F64)
    return torch.eye(3, dtype=F64) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


@pytest.mark.parametrize("mode", ["roots", "mean", "hard_mean"])
def test_relative_coordinates_in_a_rigid_frame_are_blind_to_a_rigid_motion_of_the_boundary(mode):
    """``rigid_rest``: a rigid motion of the whole scene (positions and prescribed vertices turned and moved
    together) leaves the encoded vector as it was; decoding inverts encoding; at rest the frame is the
    identity (the encoded vector is the plain coordinates'); a turn of the boundary alone (the body left
    where it was) is in the encoded vector, as the frame should see it."""
    g = torch.Generator().manual_seed(7)
    n = 9
    dirichlet, root_of = [0, 3, 6], [0, 0, 0, 3, 3, 3, 6, 6, 6]
    rest = torch.randn(n, 3, generator=g, dtype=F64)
    plain = RelativeCoordinates(n, dirichlet, mode, root_of=root_of if mode == "roots" else None)
    c = RelativeCoordinates(n, dirichlet, mode, root_of=root_of if mode == "roots" else None, rigid_rest=rest[dirichlet])
    assert c.rigid and not plain.rigid and c.dim == plain.dim
    x = rest + 0.1 * torch.randn(4, n, 3, generator=g, dtype=F64)
    xD = rest[dirichlet].expand(4, 3, 3).clone()
    if c.hard_dirichlet:
        x[:, dirichlet] = xD
    assert torch.allclose(c.encode(x, xD), plain.encode(x, xD), atol=1e-14)  # the frame at rest: the identity
    Q, t = _rotation([1.0, 2.0, -0.5], 1.1), torch.tensor([0.3, -1.0, 2.0], dtype=F64)
    moved, movedD = x @ Q.T + t, xD @ Q.T + t
    u = c.encode(moved, movedD)
    assert torch.allclose(u, c.encode(x, xD), atol=1e-13)
    assert not torch.allclose(plain.encode(moved, movedD), plain.encode(x, xD), atol=1e-2)
    assert torch.allclose(c.decode(u, movedD), moved, atol=1e-13, rtol=0)
    R, origin = c.pose(movedD)
    assert torch.allclose(R, Q.expand(4, 3, 3), atol=1e-13) and torch.allclose(origin[:, 0], movedD.mean(1), atol=1e-14)
    turned = (xD - xD.mean(1, keepdim=True)) @ Q.T + xD.mean(1, keepdim=True)  # the boundary turned, the body not
    assert not torch.allclose(c.encode(x, turned), c.encode(x, xD), atol=1e-2)


def test_an_autoencoder_in_a_rigid_frame_holds_a_turning_body_in_one_latent():
    """A body whose prescribed vertices carry it through turns about changing axes while one shape mode of it
    swells and shrinks: in the rigid frame every frame is the rest shape plus that mode, and an autoencoder of
    latent 1 reconstructs every frame to float32 rounding; in the plain coordinates the turns are in the data
    and latent 1 misses by a sizeable part of the body."""
    g = torch.Generator().manual_seed(4)
    n, D, T = 10, [0, 1, 2], 60
    rest = torch.randn(n, 3, generator=g, dtype=F64)
    shape_mode = 0.1 * torch.randn(n, 3, generator=g, dtype=F64)
    shape_mode[D] = 0.0
    t = torch.arange(T, dtype=F64)
    Q = torch.stack([_rotation([math.cos(0.1 * k), 1.0, math.sin(0.2 * k)], 0.05 * k) for k in range(T)])
    x = (rest + torch.sin(0.3 * t)[:, None, None] * shape_mode) @ Q.transpose(-1, -2) + 0.01 * t[:, None, None]
    xD = x[:, D]
    size = float(torch.linalg.vector_norm(rest - rest.mean(0), dim=-1).max())
    errors = {}
    for rigid in (True, False):
        c = RelativeCoordinates(n, D, "mean", rigid_rest=rest[D] if rigid else None)
        ae, _ = fit_autoencoder(c.encode(x, xD).float(), {"latent_dim": 1, "widths": [8], "epochs": 5, "batch_size": 20}, seed=0)
        with torch.no_grad():
            rec = decode_latents(ae, c, encode_positions(ae, c, x, xD), xD)
        errors[rigid] = float(torch.linalg.vector_norm(rec - x, dim=-1).max()) / size
    assert errors[True] < 1e-4 and errors[False] > 0.05, errors


def test_a_rigid_frame_needs_three_prescribed_vertices_off_one_line(tmp_path):
    """Two prescribed vertices, or any number on one line, span no frame: refused, naming the scene's file."""
    import h5py

    from latentsim.latent.coordinates import coordinates_for

    line = torch.tensor([[0.0, 0, 0], [1, 1, 0], [2, 2, 0], [3, 3, 0]], dtype=F64)
    for rest in (line[:2], line):
        with pytest.raises(ValueError, match=r"three prescribed vertices not on one line \(\d prescribed\)"):
            RelativeCoordinates(4, list(range(len(rest))), "mean", rigid_rest=rest)
    path = tmp_path / "trajectories.h5"
    with h5py.File(path, "w") as f:
        f["rest_positions"], f["dirichlet"] = line.numpy(), np.arange(4)
        f.attrs["model"] = "cloth"
    with h5py.File(path) as f, pytest.raises(ValueError, match=rf"{path}: rigid frame: needs"):
        coordinates_for(f, None, rigid_frame=True)


def test_boundary_inputs_in_a_rigid_frame_carry_the_program_into_it():
    """In a rigid frame p_t's 3-vectors are those the frame sees (R^T v), then the nine entries of R^T, row
    by row; NumPy and torch alike; the origin, when asked for, comes last."""
    from latentsim.latent.integrator import boundary_inputs

    g = torch.Generator().manual_seed(3)
    rest = torch.randn(4, 3, generator=g, dtype=F64)
    c = RelativeCoordinates(4, [0, 1, 2, 3], "mean", rigid_rest=rest)
    Qs = torch.stack([_rotation([0.2, 1.0, 0.3], a) for a in (0.0, 0.7, -1.9)])
    xD = rest @ Qs.transpose(-1, -2) + torch.tensor([0.5, 0.0, -1.0], dtype=F64)
    bc = torch.randn(3, 6, generator=g, dtype=F64).numpy()
    p = boundary_inputs(bc, xD.numpy(), False, c)
    assert p.shape == (3, 15)
    Qt = Qs.transpose(-1, -2).numpy()
    assert np.allclose(p[:, :3], np.einsum("tij,tj->ti", Qt, bc[:, :3]), atol=1e-13)
    assert np.allclose(p[:, 3:6], np.einsum("tij,tj->ti", Qt, bc[:, 3:]), atol=1e-13)
    assert np.allclose(p[:, 6:].reshape(3, 3, 3), Qt, atol=1e-13)
    assert np.allclose(p[0], np.concatenate([bc[0], np.eye(3).reshape(9)]), atol=1e-13)  # at rest: as given, then I
    pt = boundary_inputs(torch.as_tensor(bc, dtype=torch.float32), xD, True, c)
    assert pt.dtype == torch.float32 and pt.shape == (3, 18)
    assert torch.allclose(pt[:, :15], torch.as_tensor(p, dtype=torch.float32), atol=1e-6)
    assert torch.allclose(pt[:, 15:], xD.mean(1).float(), atol=1e-6)
    with pytest.raises(ValueError, match="not 3-vectors"):
        boundary_inputs(bc[:, :4], xD.numpy(), False, c)


def test_boundary_inputs_append_the_mean_prescribed_position():
    from latentsim.latent.integrator import boundary_inputs

    bc = np.arange(6.0).reshape(3, 2)
    xD = np.random.default_rng(0).normal(size=(3, 4, 3))
    assert boundary_inputs(bc, xD, False) is bc
    p = boundary_inputs(bc, xD, True)
    assert p.shape == (3, 5) and np.array_equal(p[:, :2], bc) and np.allclose(p[:, 2:], xD.mean(1))
    pt = boundary_inputs(torch.as_tensor(bc, dtype=torch.float32), torch.as_tensor(xD), True)
    assert pt.dtype == torch.float32 and torch.allclose(pt, torch.as_tensor(p, dtype=torch.float32))


def test_an_integrator_trained_with_the_origin_takes_it_in_training_the_file_and_the_rollout(chain_setup, tmp_path):
    """``origin_input``: the training triplets' p_t end with the frame's mean prescribed position, the
    model file keeps the setting, and a rollout of the loaded integrator feeds it the origin of each
    frame (its latents are those of stepping it by hand with them, and not those without: the program
    moves the root, so the origin changes); a conditioned training refuses it."""
    from latentsim.latent.conditioning import Conditioning
    from latentsim.latent.integrator import boundary_inputs

    ch, seqs, coords, ae = chain_setup
    integ, hist = fit_integrator(ae, coords, ch.pot, seqs, {**INTEG_CFG, "epochs": 2, "origin_input": True}, seed=0)
    assert integ.bc_dim == 4 and integ.hparams["origin"] is True
    assert "origin" not in fit_integrator(ae, coords, ch.pot, seqs, {**INTEG_CFG, "epochs": 1}, seed=0)[0].hparams
    save_module(tmp_path / "integrator.pt", integ)
    loaded = load_integrator(tmp_path / "integrator.pt")
    assert loaded.origin and loaded.bc_dim == 4
    s = seqs[2]
    z = encode_positions(ae, coords, s["positions"], s["dirichlet_positions"])
    res = rollout(loaded, ae, coords, z[0], z[1], s["bc"], s["dirichlet_positions"])
    p = torch.as_tensor(boundary_inputs(s["bc"], s["dirichlet_positions"], True), dtype=torch.float32)
    zs = [z[0], z[1]]
    with torch.no_grad():
        for t in range(2, 6):
            zs.append(loaded(zs[-1][None], zs[-2][None], p[t : t + 1], p[t - 1 : t], p[t - 2 : t - 1])[0])
        blind = loaded(zs[1][None], zs[0][None], torch.cat([p[2:3, :1], torch.zeros(1, 3)], -1), torch.cat([p[1:2, :1], torch.zeros(1, 3)], -1), p[0:1])[0]
    assert torch.allclose(res["latents"][:6], torch.stack(zs), atol=1e-5)
    assert not torch.allclose(res["latents"][2], blind, atol=1e-5)
    free = [{**q, "dirichlet_positions": q["dirichlet_positions"][:, :0]} for q in seqs]
    with pytest.raises(ValueError, match="origin_input needs prescribed vertices"):
        fit_integrator(ae, coords, ch.pot, free, {**INTEG_CFG, "origin_input": True})
    with pytest.raises(ValueError, match="origin_input is not for a conditioned integrator"):
        fit_integrator(ae, coords, ch.pot, seqs, {**INTEG_CFG, "origin_input": True},
                       conditioning=Conditioning((ch.pot.dt, ch.pot.dt), (1.0, 1.0), ch.pot.dt, 1.0))  # fmt: skip
    turning = copy.copy(coords)
    turning.rigid = True  # an autoencoder with rigid_frame: refused the same way
    with pytest.raises(ValueError, match="rigid_frame: not for a conditioned scene"):
        fit_integrator(ae, turning, ch.pot, seqs, INTEG_CFG, conditioning=Conditioning((ch.pot.dt, ch.pot.dt), (1.0, 1.0), ch.pot.dt, 1.0))

"""A new energy is one PyTorch function: a toy term with ``local_energy`` only (no compiled kernels)
registered as a material with one line runs in the full-space solver, in the training loss and in
a reduced solver.

The toy is the rod's edge spring 1/2 ks (|e|/|ebar| - 1)^2 |ebar| written again, so every result
must equal, to rounding, the scene whose springs are the compiled ``rods.RodStretch``: a wrong
autograd gradient or Hessian, a wrong scatter into the sparse pattern or a wrong projection would
move the solves apart.  The assembled gradient and Hessian are also checked against finite
differences of the energy, and the Newton steps against the solver's force tolerance.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from latentsim.latent import Autoencoder, RelativeCoordinates
from latentsim.latent.autoencoder import decode_latents
from latentsim.latent.loss import integrator_loss
from latentsim.latent.subspaces import LinearSubspace
from latentsim.mesh import rod_bundle
from latentsim.physics.base import EnergyTerm
from latentsim.physics.kernels import with_compiled_elastic
from latentsim.physics.materials import MATERIALS, register
from latentsim.physics.rods import RodBend, rod_stiffness, rod_topology
from latentsim.scene import build_potential
from latentsim.solve.assembly import AutogradKernel
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings
from latentsim.solve.reduced import ReducedSettings, reduced_rollout

DT = 0.01
MATERIAL = {"youngs_modulus": 1e5, "poisson_ratio": 0.35, "density": 1000.0, "radius": 1e-3}


class ToySpring(EnergyTerm):
    """1/2 ks (|e|/|ebar| - 1)^2 |ebar| per edge: ``local_energy`` and nothing else."""

    name = "toy_spring"

    def __init__(self, X, edges, ks):
        self.stencils = torch.as_tensor(edges, dtype=torch.long)
        self.rest_length = (X[self.stencils[:, 1]] - X[self.stencils[:, 0]]).norm(dim=-1)
        self.ks = float(ks)

    def local_energy(self, xe):
        length = (xe[..., 1, :] - xe[..., 0, :]).norm(dim=-1)
        return 0.5 * self.ks * (length / self.rest_length - 1.0) ** 2 * self.rest_length


def toy_terms(X, st, material):
    ks, kb = rod_stiffness(float(material["youngs_modulus"]), float(material["radius"]))
    return [ToySpring(X, st["edges"], ks), RodBend(X, st["triples"], kb)]  # beside a compiled term


@pytest.fixture(scope="module", autouse=True)
def toy_material():
    register("toy_spring", "rods", toy_terms, "toy springs beside the rods' bending (tests)")  # the one line
    yield
    del MATERIALS["toy_spring"]


def scene(law, springs_only=False):
    """Three hanging rods of 7 vertices, their two top vertices clamped; the toy or the compiled springs."""
    X, edges, roots = rod_bundle(3, 7, 0.15, 0.05)
    _, triples = rod_topology(3, 7)
    arrays = {"rest_positions": X, "edges": edges, "triples": triples.numpy(), "dirichlet": np.concatenate([roots, roots + 1])}
    pot = build_potential("rods", arrays, {**MATERIAL, "model": law}, DT, [0.0, -9.81, 0.0])
    if springs_only:
        pot.terms = pot.terms[:1]
    return pot, np.asarray(X)


def clamp_path(X, D, frames):
    """The clamp moving sideways and up (m, 3) per frame."""
    return np.stack([X[D] + [0.01 * t, 0.004 * t, 0.0] for t in range(frames)])


def test_the_solver_runs_the_toy_through_autograd_and_its_derivatives_are_its_energy_s():
    """Assembled gradient and exact Hessian of the toy alone: central differences of its energy;
    and, exact and projected, the compiled springs' to rounding."""
    toy, X = scene("toy_spring", springs_only=True)
    ref, _ = scene("stvk", springs_only=True)
    solver, compiled = ImplicitEuler(toy, threads=1), ImplicitEuler(ref, threads=1)
    assert isinstance(solver.assembly.kernels[0], AutogradKernel)
    rng = np.random.default_rng(0)
    x = X + 0.01 * rng.standard_normal(X.shape)
    x[:, 1] *= 1.1  # springs stretched, some compressed: the projection clamps those
    diag = np.zeros(x.size)
    e, g, U = solver.assembly.energy_gradient_hessian(x, diag, project=False)
    energy = solver.assembly.energy
    assert e == pytest.approx(float(toy.elastic(torch.as_tensor(x))), rel=1e-13)
    h = 1e-6
    fd = np.array([(energy(x + h * d.reshape(x.shape)) - energy(x - h * d.reshape(x.shape))) / (2 * h) for d in np.eye(x.size)])
    assert np.abs(g - fd).max() <= 1e-6 * np.abs(g).max()
    free = solver.free_dofs
    H = U.tocsr().toarray()  # (the rods' linear solver is banded: BandedUpper)
    H = H + np.triu(H, 1).T
    grad_at = lambda y: solver.assembly.energy_gradient(y)[1][free]  # noqa: E731
    for j, dof in enumerate(free[::7]):
        d = np.zeros(x.size)
        d[dof] = h
        col = (grad_at(x + d.reshape(x.shape)) - grad_at(x - d.reshape(x.shape))) / (2 * h)
        assert np.abs(H[:, np.searchsorted(free, dof)] - col).max() <= 1e-5 * np.abs(H).max()
    for project in (False, True):
        e, g, U = solver.assembly.energy_gradient_hessian(x, diag, project)
        e2, g2, U2 = compiled.assembly.energy_gradient_hessian(x, diag, project)
        assert e == pytest.approx(e2, rel=1e-12) and np.abs(g - g2).max() <= 1e-11 * np.abs(g2).max()
        U, U2 = U.tocsr().toarray(), U2.tocsr().toarray()
        assert np.abs(U - U2).max() <= 1e-10 * np.abs(U2).max()
    _, _, Up = solver.assembly.energy_gradient_hessian(x, diag, True)
    Hp = Up.tocsr().toarray()
    Hp = Hp + np.triu(Hp, 1).T
    assert np.linalg.eigvalsh(H).min() < -1e-3 * np.abs(H).max()  # the exact Hessian is indefinite here
    assert np.linalg.eigvalsh(Hp).min() > -1e-9 * np.abs(Hp).max()  # the projected one is not


def test_implicit_euler_with_the_toy_matches_the_compiled_springs():
    """A few Newton steps of the mixed scene (toy springs by autograd, bending compiled): each step
    converged to the solver's force tolerance, and the frames those of the compiled scene."""
    toy, X = scene("toy_spring")
    ref, _ = scene("stvk")
    settings = NewtonSettings(tolerance=1e-9)
    a, b = ImplicitEuler(toy, settings, threads=2), ImplicitEuler(ref, settings, threads=2)
    xD = clamp_path(X, a.dirichlet, 8)
    xa, xb = [X, X], [X, X]
    for t in range(2, len(xD)):
        x, info = a.step(xa[-1], xa[-2], xD[t])
        assert info.gradient_norm <= settings.tolerance * a.f_ref
        grad = a._evaluate(x, xa[-1], xa[-2])[1]
        assert np.linalg.norm(grad[a.free_dofs]) <= settings.tolerance * a.f_ref
        xa.append(x)
        xb.append(b.step(xb[-1], xb[-2], xD[t])[0])
    moved = np.abs(xa[-1] - X).max()
    assert moved > 0.01
    assert np.abs(xa[-1] - xb[-1]).max() <= 1e-8 * moved


def test_the_training_loss_evaluates_the_toy_on_decoded_states():
    """The self-supervised loss of a batch of decoded states, and its gradient in the integrator's
    weights: the toy scene's (PyTorch, as training leaves a potential with a term without kernels)
    equal the compiled scene's."""
    toy, X = scene("toy_spring")
    ref, _ = scene("stvk")
    toy_c, ref_c = with_compiled_elastic(toy), with_compiled_elastic(ref)
    assert toy_c.kernels is None and ref_c.kernels is not None
    D = toy.dirichlet.numpy()
    coords = RelativeCoordinates(len(X), D, "mean")
    torch.manual_seed(0)
    rest = coords.encode(torch.as_tensor(X), torch.as_tensor(X[D]))
    ae = Autoencoder(coords.dim, 3, [16], pca_dim=3).double()
    ae.init_pca(rest + 0.01 * torch.randn(32, coords.dim, dtype=torch.float64))
    ae.eval()
    B = 5
    z = 0.1 * torch.randn(B, 3, dtype=torch.float64)
    xD = torch.as_tensor(clamp_path(X, D, 3)).expand(B, 3, len(D), 3)
    batch = {"z": 1.1 * z, "z_prev": z, "z_prev2": 0.9 * z, "p": torch.zeros(B, 6), "p_prev": torch.zeros(B, 6), "p_prev2": torch.zeros(B, 6),
             "xD": xD[:, 2], "xD_prev": xD[:, 1], "xD_prev2": xD[:, 0]}  # fmt: skip (z: the rows' ground truth, unused here)
    step = torch.nn.Linear(3, 3, dtype=torch.float64)

    def integrator(z1, z2, p, p1, p2):
        return 2.0 * z1 - z2 + 0.01 * step(z1)

    losses, grads = [], []
    for pot in (toy_c, ref_c):
        step.zero_grad()
        loss, info = integrator_loss(integrator, ae, coords, pot, batch, noise_scale=0.0)
        loss.backward()
        losses.append(info["per_sample"])
        grads.append(step.weight.grad.clone())
    assert torch.allclose(losses[0], losses[1], rtol=1e-11, atol=0)
    assert torch.allclose(grads[0], grads[1], rtol=1e-8, atol=1e-12 * float(grads[1].abs().max()))
    x = decode_latents(ae, coords, z, batch["xD"])
    assert torch.allclose(toy.terms[0].energy(x), ref.terms[0].energy(x), rtol=1e-12, atol=0)


def test_a_reduced_solver_runs_the_toy():
    """Reduced implicit Euler in a 6-dimensional linear subspace: the toy scene's rollout is the
    compiled scene's, and each step meets the reduced solver's tolerance."""
    toy, X = scene("toy_spring")
    ref, _ = scene("stvk")
    D = toy.dirichlet.numpy()
    coords = RelativeCoordinates(len(X), D, "roots", root_of=[int(D[0])] * len(X))
    u0 = coords.encode(torch.as_tensor(X), torch.as_tensor(X[D])).numpy()
    basis = np.linalg.qr(np.random.default_rng(3).standard_normal((coords.dim, 6)))[0]
    sub = LinearSubspace(coords, u0, basis)
    xD = clamp_path(X, D, 6)
    q0 = sub.project(X, xD[0])
    runs = [reduced_rollout(sub, pot, q0, q0, xD, ReducedSettings(tolerance=1e-9)) for pot in (toy, ref)]
    for out in runs:
        assert out["diverged_frame"] == -1 and out["failure"] == ""
    moved = np.abs(runs[1]["positions"][-1] - X).max()
    assert moved > 0.01
    assert np.abs(runs[0]["positions"] - runs[1]["positions"]).max() <= 1e-7 * moved

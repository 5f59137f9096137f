"""Cubature of reduced elastic forces (latentsim.solve.cubature): the greedy NNLS, the
weighted element subset, and reduced implicit Euler with it against without it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from latentsim.solve.cubature import Cubature, box_samples, cubature_potential, fit_cubature, greedy_nnls, reduced_element_forces
from latentsim.physics.base import EnergyTerm
from latentsim.mesh import beam_tets
from latentsim.solve.reduced import ReducedSettings, reduced_rollout
from latentsim.scene import build_potential
from latentsim.solve.implicit_euler import ImplicitEuler
from latentsim.solve.modes import lowest_modes
from test_kernels import MODELS, scene, states  # the small tets / rods / shell scenes

DT = 1.0 / 30.0


class ModalSubspace:
    """x = X + U q over the lowest modes, the clamp fixed: the reduced solver's subspace contract."""

    def __init__(self, V, D, U, free):
        self.X = V.reshape(-1).copy()
        self.dirichlet = D
        self.hard_dirichlet = True
        self.dim = U.shape[1]
        self.n_vertices = len(V)
        self.U = np.zeros((V.size, self.dim))
        self.U[free] = U

    def map(self, q, xD):
        return (self.X + self.U @ np.asarray(q)).reshape(-1, 3)

    def jacobian(self, q, xD):
        return self.map(q, xD), self.U

    def project(self, x, xD):
        return np.linalg.lstsq(self.U, np.asarray(x).reshape(-1) - self.X, rcond=None)[0]


@pytest.fixture(scope="module")
def beam():
    """A clamped 0.8 m beam of 160 tets and its 4 lowest modes (amplitudes up to 1 bend it ~0.25 m)."""
    V, T = beam_tets(8, 2, 2, 0.8, 0.2, 0.2, tets_per_cell=5)
    D = np.flatnonzero(V[:, 0] < 1e-12)
    mat = {"youngs_modulus": 1e5, "poisson_ratio": 0.3, "density": 1000.0}
    pot = build_potential("tets", {"rest_positions": V, "tets": T, "dirichlet": D}, mat, DT, [0.0, -9.81, 0.0])
    _, U, free = lowest_modes(pot, 4, V)
    return V, D, pot, ModalSubspace(V, D, U, free)


def test_greedy_nnls_finds_a_sparse_non_negative_combination():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((80, 300))
    truth = np.zeros(300)
    truth[[7, 42, 199]] = [1.0, 2.5, 0.5]
    index, w, history = greedy_nnls(A, A @ truth, 1e-10, 50)
    assert history[-1][1] < 1e-10
    assert (w > 0).all() and len(index) <= 6  # not a dense fit: a few columns explain it
    np.testing.assert_allclose(np.bincount(index, weights=w, minlength=300)[[7, 42, 199]], [1.0, 2.5, 0.5], rtol=1e-8)
    # unreachable tolerance: stops at max_elements
    index, _, history = greedy_nnls(rng.standard_normal((80, 300)), rng.standard_normal(80), 1e-12, 5)
    assert len(index) <= 5 and history[-1][1] > 1e-12
    with pytest.raises(ValueError, match="target is zero"):
        greedy_nnls(A, np.zeros(80), 0.1, 5)


def test_element_forces_sum_to_the_reduced_gradient(beam):
    V, D, pot, sub = beam
    q = np.array([1.5, -1.0, 0.7, 0.3])
    a = reduced_element_forces(pot.terms[0], sub, q[None])[0]  # (r, E)
    x = torch.as_tensor(sub.map(q, None)).requires_grad_(True)
    (g,) = torch.autograd.grad(pot.elastic(x), x)
    np.testing.assert_allclose(a.sum(-1), sub.U.T @ g.numpy().reshape(-1), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("model", MODELS)
def test_weighted_subsets_scale_element_energies_and_serve_the_solver(model):
    """Every elastic term: the subset's energy is sum w_e E_e, and all stencils at weight one
    give the solver (compiled kernels) the same gradient and Hessian as the term itself."""
    pot, X = scene(model)
    x = states(X, seed=3)[1]
    rng = np.random.default_rng(2)
    xt = torch.as_tensor(x)
    for term in pot.terms:
        E = len(term.stencils)
        idx = rng.choice(E, size=min(5, E), replace=False)
        w = rng.uniform(0.1, 3.0, size=len(idx))
        np.testing.assert_allclose(float(term.weighted_subset(idx, w).energy(xt)), float(term.element_energy(xt).numpy()[idx] @ w), rtol=1e-11)
        with pytest.raises(ValueError, match="non-negative"):
            term.weighted_subset(idx, -w)
        with pytest.raises(ValueError, match="out of range"):
            term.weighted_subset(np.array([E]), np.ones(1))
    sizes = tuple(len(t.stencils) for t in pot.terms)
    every = cubature_potential(pot, Cubature(np.arange(sum(sizes)), np.ones(sum(sizes)), sizes, 0.0))
    x1 = X + 0.01
    g0, H0 = ImplicitEuler(pot).gradient_hessian(x, x1, X)
    g1, H1 = ImplicitEuler(every).gradient_hessian(x, x1, X)
    np.testing.assert_allclose(g1, g0, rtol=1e-10, atol=1e-12 * np.abs(g0).max())
    assert abs(H1.tocsr() - H0.tocsr()).max() <= 1e-10 * abs(H0.tocsr()).max()


def test_cubature_splits_over_terms_and_checks_their_sizes():
    pot, X = scene("shell")  # membrane and hinge terms
    sizes = tuple(len(t.stencils) for t in pot.terms)
    cub = Cubature(np.array([1, sizes[0] + 2, sizes[0] + 3]), np.array([0.5, 2.0, 1.0]), sizes, 0.0)
    (i0, w0), (i1, w1) = cub.per_term()
    assert i0.tolist() == [1] and i1.tolist() == [2, 3] and w1.tolist() == [2.0, 1.0]
    sub = cubature_potential(pot, cub)
    xt = torch.as_tensor(states(X, seed=4)[0])
    expect = 0.5 * float(pot.terms[0].element_energy(xt)[1]) + float(pot.terms[1].element_energy(xt)[[2, 3]] @ torch.tensor([2.0, 1.0], dtype=torch.float64))
    np.testing.assert_allclose(float(sub.elastic(xt)), expect, rtol=1e-11)
    with pytest.raises(ValueError, match="fitted on terms"):
        cubature_potential(pot, Cubature(np.array([0]), np.ones(1), (sizes[0],), 0.0))


def test_cubature_fits_held_out_poses_with_few_elements(beam):
    V, D, pot, sub = beam
    E = len(pot.terms[0].stencils)
    cub = fit_cubature(pot.terms[0], sub, box_samples(4, 1.0, 100, seed=0), tolerance=0.01, validation=box_samples(4, 1.0, 50, seed=1))
    assert cub.train_error <= 0.01
    assert cub.validation_error < 0.03  # generalises to poses it never saw
    assert len(cub.index) < E / 4 and (cub.weights > 0).all()
    # the weights integrate: their sum is of the order of the element count
    assert 0.2 * E < cub.weights.sum() < 5 * E


def test_reduced_rollout_with_cubature_follows_the_exact_reduced_rollout(beam):
    """The beam falls from rest under gravity, clamped, and swings; a fine cubature tracks the
    every-element reduced solve and a coarse one does worse."""
    V, D, pot, sub = beam
    xD = np.repeat(V[D][None], 30, axis=0)
    q0 = np.zeros(4)
    settings = ReducedSettings(tolerance=1e-9)
    exact = reduced_rollout(sub, pot, q0, q0, xD, settings)
    fine = fit_cubature(pot.terms[0], sub, box_samples(4, 1.0, 100, seed=0), tolerance=0.002)
    coarse = fit_cubature(pot.terms[0], sub, box_samples(4, 1.0, 100, seed=0), tolerance=0.3)
    runs = [reduced_rollout(sub, cubature_potential(pot, c), q0, q0, xD, settings) for c in (fine, coarse)]
    assert exact["diverged_frame"] == -1 and all(r["diverged_frame"] == -1 for r in runs)
    sag = np.abs(exact["positions"] - V).max()
    assert sag > 0.05  # it really bends
    err_fine, err_coarse = (np.abs(r["positions"] - exact["positions"]).max() / sag for r in runs)
    print(f"sag {sag:.3f} m, cubature error fine {err_fine:.2e} ({len(fine.index)} tets), coarse {err_coarse:.2e} ({len(coarse.index)})")
    # the beam's two bending modes share a frequency: the basis of that pair the eigensolver returns
    # (and the sign convention) decides which poses the samples cover, and moves this from ~0.015 to 0.022
    assert err_fine < 0.03
    assert err_coarse > 2 * err_fine  # the fit's tolerance is what buys the accuracy
    assert len(fine.index) < len(pot.terms[0].stencils) / 3


def test_cubature_potential_names_unsupported_terms(beam):
    V, D, pot, sub = beam

    class Springs(EnergyTerm):  # a term without weighted_subset
        name = "springs"
        stencils = torch.zeros((1, 2), dtype=torch.long)

    odd = dataclasses.replace(pot, terms=[Springs()])
    with pytest.raises(ValueError, match="'springs'"):
        cubature_potential(odd, Cubature(np.array([0]), np.ones(1), (1,), 0.0))

r"""Optimised cubature for reduced elastic forces (An, Kim and James 2008).

A reduced solver that evaluates every element costs as much per iteration as
the full-space one.  Cubature replaces the elastic energy by a weighted sum
over a few elements,

    E(x) = sum_e E_e(x)  ~  sum_{e in C} w_e E_e(x),     w_e >= 0,

with C and w fitted so that the *reduced* forces match on training poses
q_s of the subspace x = phi(q):

    f_s = J_s^T grad E(x_s) = sum_e a_{s,e},   a_{s,e} = J_s^T grad E_e(x_s)  (r,),

    min_{w >= 0} sum_s || sum_e w_e a_{s,e} - f_s ||^2 / ||f_s||^2,

solved greedily: add the element whose column best matches the residual,
re-solve the non-negative least squares over the chosen set (An et al.'s
greedy NNLS), until the relative residual falls below a tolerance.  The
weighted sum is itself an elastic energy (non-negative weights of element
energies), so the reduced implicit-Euler step with it stays a minimisation
and needs nothing new: :func:`cubature_potential` returns an
:class:`IncrementalPotential` whose elastic term is the weighted subset (the
inertia and gravity stay exact, over every vertex).

Element gradients come from the terms' own ``local_energy`` by autograd, and
the weighted potential from each term's ``weighted_subset`` (every elastic
term of the package: tets, rod stretch and bend, shell membrane and hinge).
A scene with several terms gets one fit over all their elements (the
columns of every term side by side).  Poses are drawn by the caller: e.g.
:func:`box_samples` over a Neural Modes training box (data-free), or the
subspace's projections of training frames (Fulton et al. 2019).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.optimize import nnls

from latentsim.physics.incremental_potential import IncrementalPotential

__all__ = ["Cubature", "box_samples", "check_supported", "reduced_element_forces", "greedy_nnls", "fit_cubature", "cubature_potential"]


@dataclass
class Cubature:
    """Elements and weights of a cubature of a potential's elastic terms, and how well it fits.

    index : (k,) indices into the terms' stencils laid end to end (term 0's
    first); weights : (k,) >= 0; sizes : stencil count of each term.
    train_error, validation_error : relative reduced-force error
    ``||A w - f|| / ||f||`` over the (row-normalised) training / validation poses.
    fit_seconds : wall time of the fit.
    """

    index: np.ndarray
    weights: np.ndarray
    sizes: tuple
    train_error: float
    validation_error: float = float("nan")
    fit_seconds: float = 0.0
    history: list = field(default_factory=list)  # (elements, train error) after each greedy step

    @property
    def n_elements(self) -> int:
        return int(sum(self.sizes))

    def per_term(self):
        """[(index into term i's stencils, weights)] for each term."""
        edges = np.cumsum((0,) + tuple(self.sizes))
        return [
            (self.index[(self.index >= a) & (self.index < b)] - a, self.weights[(self.index >= a) & (self.index < b)])
            for a, b in zip(edges[:-1], edges[1:])
        ]


def box_samples(m: int, box: float, count: int, seed: int = 0) -> np.ndarray:
    """(count, m) coordinates uniform in [-box, box]^m, each scaled by a factor uniform in
    [0.05, 1] so that poses near the origin (small forces, equal weight after the row
    normalisation) are as well represented as the box's corners."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-box, box, size=(count, m))
    return q * rng.uniform(0.05, 1.0, size=(count, 1))


def reduced_element_forces(terms, subspace, samples, xD=None) -> np.ndarray:
    """Per-element reduced forces a_{s,e} = J_s^T grad E_e(phi(q_s)).

    Parameters
    ----------
    terms : an energy term (``stencils`` (E, k), ``local_energy``) or a list of them.
    subspace : object with ``jacobian(q, xD) -> (x (n,3), J (3n, r))``,
        ``dirichlet`` and ``hard_dirichlet`` (the reduced solver's contract).
    samples : (S, r) reduced coordinates.
    xD : (m, 3) prescribed positions during the fit (default: the rest ones,
        which elastic energy's rigid-motion invariance makes general), or
        (S, m, 3), one per sample (poses taken from simulated frames).

    Returns
    -------
    (S, r, E) float64, E the terms' stencils end to end.  Rows of prescribed
    DoFs are dropped when the subspace imposes them exactly (the solver
    eliminates those DoFs too).
    """
    terms = list(terms) if isinstance(terms, (list, tuple)) else [terms]
    samples = np.atleast_2d(np.asarray(samples, dtype=np.float64))
    D = np.asarray(subspace.dirichlet, dtype=np.int64)
    xD = _rest_dirichlet(subspace) if xD is None else np.asarray(xD, dtype=np.float64)
    if xD.ndim == 2:
        xD = np.broadcast_to(xD, (len(samples),) + xD.shape)
    if len(xD) != len(samples):
        raise ValueError(f"{len(samples)} samples but {len(xD)} prescribed-position sets")
    out = []
    for q, xd in zip(samples, xD):
        x, J = subspace.jacobian(q, xd)
        J3 = np.array(J, dtype=np.float64).reshape(len(x), 3, -1)
        if subspace.hard_dirichlet and len(D):
            J3[D] = 0.0
        xt = torch.as_tensor(np.asarray(x, dtype=np.float64))
        cols = []
        for term in terms:
            st = term.stencils.cpu().numpy()
            xe = xt[torch.as_tensor(st)].requires_grad_(True)
            (g,) = torch.autograd.grad(term.local_energy(xe).sum(), xe)
            cols.append(np.einsum("eac,eacr->re", g.numpy(), J3[st]))
        out.append(np.concatenate(cols, axis=1))
    return np.stack(out)


def _rest_dirichlet(subspace):
    X = getattr(subspace, "X", None)
    if X is None:
        raise ValueError("pass xD: the subspace does not hold its rest positions")
    return np.asarray(X, dtype=np.float64).reshape(-1, 3)[np.asarray(subspace.dirichlet, dtype=np.int64)]


def greedy_nnls(A: np.ndarray, b: np.ndarray, tolerance: float, max_elements: int, batch: int = 1):
    """Sparse non-negative w with ||A w - b|| <= tolerance ||b|| (An et al. 2008).

    Each round adds the ``batch`` unchosen columns most aligned with the
    residual (largest positive A_e^T r / ||A_e||), re-solves the NNLS over the
    chosen set and drops the columns it zeroes.

    Returns
    -------
    index (k,), weights (k,), history [(k, relative residual)].
    """
    A = np.asarray(A, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    bn = float(np.linalg.norm(b))
    if bn == 0.0:
        raise ValueError("greedy_nnls: the target is zero (no forces at the training poses?)")
    norms = np.linalg.norm(A, axis=0)
    usable = norms > 1e-14 * max(float(norms.max()), 1e-300)
    chosen = np.zeros(0, dtype=np.int64)
    w = np.zeros(0)
    residual = b.copy()
    history = []
    while True:
        rel = float(np.linalg.norm(residual)) / bn
        history.append((len(chosen), rel))
        if rel <= tolerance or len(chosen) >= max_elements:
            break
        score = np.where(usable, A.T @ residual / np.where(usable, norms, 1.0), -np.inf)
        score[chosen] = -np.inf
        new = np.argsort(score)[::-1][:batch]
        new = new[score[new] > 0]
        if not len(new):
            break  # no column decreases the residual any more
        chosen = np.concatenate([chosen, new])
        w, _ = nnls(A[:, chosen], b, maxiter=50 * len(chosen) + 100)
        keep = w > 0
        chosen, w = chosen[keep], w[keep]
        residual = b - A[:, chosen] @ w
    return chosen, w, history


def fit_cubature(terms, subspace, samples, tolerance: float = 0.01, max_elements: int = 400, validation=None, xD=None, batch: int = 1) -> Cubature:
    """Fit a cubature of ``terms`` (one or a list; normally ``potential.terms``) to the
    reduced forces of ``subspace`` at ``samples``.

    Each pose's rows are divided by its total force norm (An et al.), so small
    deformations count as much as large ones; poses with no force are skipped.
    ``validation`` : optional (V, r) poses to report the error on.
    """
    t0 = time.perf_counter()
    terms = list(terms) if isinstance(terms, (list, tuple)) else [terms]
    A, b = _normalised(reduced_element_forces(terms, subspace, samples, xD))
    index, weights, history = greedy_nnls(A, b, tolerance, max_elements, batch)
    cub = Cubature(index, weights, tuple(int(t.stencils.shape[0]) for t in terms), history[-1][1], history=history)
    cub.fit_seconds = time.perf_counter() - t0
    if validation is not None:
        Av, bv = _normalised(reduced_element_forces(terms, subspace, validation, xD))
        cub.validation_error = float(np.linalg.norm(Av[:, index] @ weights - bv) / np.linalg.norm(bv))
    return cub


def _normalised(A):
    """(S, r, E) -> rows (S r, E) and target (S r,), each pose scaled to unit total force."""
    f = A.sum(-1)  # (S, r)
    fn = np.linalg.norm(f, axis=1)
    ok = fn > 1e-12 * max(float(fn.max()), 1e-300)
    A, f, fn = A[ok], f[ok], fn[ok]
    return (A / fn[:, None, None]).reshape(-1, A.shape[-1]), (f / fn[:, None]).reshape(-1)


def check_supported(potential: IncrementalPotential) -> None:
    """Raise ValueError unless every elastic term has ``weighted_subset``."""
    for term in potential.terms:
        if not hasattr(term, "weighted_subset"):
            raise ValueError(f"cubature for the '{term.name}' term is not implemented (no weighted_subset)")


def cubature_potential(potential: IncrementalPotential, cubature: Cubature) -> IncrementalPotential:
    """``potential`` with each elastic term replaced by its weighted subset of the cubature.

    Inertia, gravity, masses and the Dirichlet set are unchanged (exact, over
    every vertex); a term the cubature gives no element is left out.  Raises
    ValueError when a term has no ``weighted_subset`` or the stencil counts
    differ from the fit's.
    """
    check_supported(potential)
    sizes = tuple(int(t.stencils.shape[0]) for t in potential.terms)
    if sizes != tuple(cubature.sizes):
        raise ValueError(f"the cubature was fitted on terms of {tuple(cubature.sizes)} stencils; the potential's have {sizes}")
    terms = [t.weighted_subset(i, w) for t, (i, w) in zip(potential.terms, cubature.per_term()) if len(i)]
    return dataclasses.replace(potential, terms=terms)

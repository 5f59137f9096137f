r"""Neural Modes (Wang et al. 2024): linear modes, the nonlinear modal map, its loss and ground truth.

Linear modes (paper Sec. 3.2).  The lowest eigenpairs of the rest-state
elastic Hessian generalised with the lumped mass matrix,

    K e_i = omega_i^2 M e_i,

found by shift-invert Lanczos (``solver.lowest_modes``: ``eigsh``, never a dense
matrix).  With Dirichlet constraints the prescribed DoFs are removed.  A
free-floating object has six zero modes (rigid translations and rotations);
K is singular there, so the shift is a small *negative* sigma (K - sigma M is
positive definite), the k + 6 lowest pairs are computed, and the six whose
span is the rigid space (checked against the explicit rigid basis R) are
dropped; the kept modes are projected M-orthogonally off span(R).

Neural Modes (Eq. 10-13).  For modal coordinates z (m,) and optional
auxiliary inputs a (material/shape parameters),

    n(z) = X + l(z) + y(z),    l(z) = sum_i z_i e_i,    y = MLP(z, a)  (GELU),

trained by minimising, over samples z drawn uniformly in a box (stochastic)
or on a regular grid,

    L = mean_z [ E(X + l + y) + lambda (l^T y)^2 ] + eta ||y(0)||^2,

E the scene's elastic energy only (``IncrementalPotential.elastic``: no
inertia, gravity or Dirichlet penalty).  ``orthogonality='unit'`` uses
(l^T y / |l|)^2 instead of the paper's (l^T y)^2; ``orthogonality='exact'``
builds the constraint into the map instead, y <- y - l (l^T y) / (l^T l)
(l^T M y and l^T M l with ``metric='mass'``), so l^T y = 0 holds to round-off
and the loss is the energy alone: the constrained problem of Eq. 9 itself
rather than its penalty, which on the sheet trains to a tenth of the energy
error in the same epochs (the penalty's large lambda makes the loss stiff).

Ground truth (Eq. 9).  Nonlinear compliant modes per sample,

    n(z) = argmin_x E(x)   s.t.   l^T (x - X - l) = 0   (i.e. l^T y = 0),

by Newton's method on the KKT system of the single linear constraint, with
the terms' closed-form per-stencil Hessians assembled sparsely
(``latentsim.solve.sparse``): the direction dx solves

    [H  c] [dx]   [-g]
    [c' 0] [mu] = [ 0],    c = l (free DoFs),

by two solves with one factorisation of H (Schur complement of the 1x1
block).  Iterates stay feasible (c^T dx = 0), and a backtracking line search
on E keeps the energy decreasing.  For a free-floating object the rigid
motions that keep l^T y = 0 leave E unchanged; a tiny multiple of M is added
to H (Levenberg) so that the solve is defined.  The exact Hessian is used
when it yields a descent direction, the per-stencil PSD projection
otherwise.
"""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from latentsim.physics.incremental_potential import IncrementalPotential
from latentsim.physics.kernels import with_compiled_elastic
from latentsim.solve.modes import fix_sign, lowest_modes
from latentsim.solve.constrained import ConstrainedNewton

log = logging.getLogger(__name__)

__all__ = [
    "NM_DEFAULTS",
    "LinearModes",
    "NeuralModes",
    "direction_correlation",
    "fixed_dofs",
    "from_config",
    "ground_truth",
    "latent_directions",
    "linear_modes",
    "load_neural_modes",
    "make_optimizer",
    "modal_samples",
    "neural_modes_from_state",
    "neural_modes_loss",
    "optimizer_step",
    "rigid_modes",
    "train_neural_modes",
]


# --------------------------------------------------------------------------------------------------
# linear modes
# --------------------------------------------------------------------------------------------------
@dataclass
class LinearModes:
    """Lowest vibration modes of a scene.

    Attributes
    ----------
    omega2 : (k,) eigenvalues omega^2 [1/s^2], ascending.
    modes : (3n, k) modes over all DoFs (zero on prescribed DoFs), normalised
        as ``normalization`` says: 'mass' (e^T M e = 1) or 'euclidean' (|e| = 1).
    free_dofs : (f,) the DoFs the eigenproblem ran on.
    rigid_removed : 6 for a free-floating object, else 0.
    normalization : 'mass' | 'euclidean'.
    """

    omega2: np.ndarray
    modes: np.ndarray
    free_dofs: np.ndarray
    rigid_removed: int
    normalization: str


def rigid_modes(X, masses) -> np.ndarray:
    """M-orthonormal basis (3n, 6) of rigid motions of rest positions X (n,3): 3 translations, 3 rotations."""
    X = np.asarray(X, dtype=np.float64)
    m3 = np.repeat(np.asarray(masses, dtype=np.float64), 3)
    c = np.average(X, axis=0, weights=np.asarray(masses, dtype=np.float64))
    r = X - c
    n = len(X)
    R = np.zeros((3 * n, 6))
    for a in range(3):
        R[a::3, a] = 1.0
        w = np.zeros(3)
        w[a] = 1.0
        R[:, 3 + a] = np.cross(w, r).reshape(-1)
    # M-orthonormalise (Gram-Schmidt in the M inner product, via Cholesky of the Gram matrix)
    G = R.T @ (m3[:, None] * R)
    Lc = np.linalg.cholesky(G)
    return np.linalg.solve(Lc, R.T).T


def fixed_dofs(dirichlet, boundary: str) -> np.ndarray:
    """The DoFs the modes and the correction leave at rest: every DoF of the ``dirichlet`` vertices with
    ``boundary='dirichlet'``, none with 'free'."""
    if boundary == "free":
        return np.zeros(0, dtype=np.int64)
    D = np.asarray(dirichlet, dtype=np.int64)
    return (3 * D[:, None] + np.arange(3)).reshape(-1)


def linear_modes(
    potential: IncrementalPotential, k: int, x, boundary: str = "dirichlet", normalization: str = "mass", tol: float = 0.0
) -> LinearModes:
    """The k lowest non-rigid modes of K e = omega^2 M e at ``x``.

    Parameters
    ----------
    potential : the scene's potential (its elastic terms and lumped masses; its
        ``dirichlet`` set is removed when ``boundary='dirichlet'``).
    k : number of modes.
    x : (n,3) state at which K is evaluated, normally the rest state (only
        there is K positive semi-definite, which the shift-invert needs).
    boundary : 'dirichlet' (remove the prescribed DoFs) or 'free' (all DoFs
        free; the six rigid modes are removed).
    normalization : 'mass' (e^T M e = 1) or 'euclidean' (|e|_2 = 1, the
        scaling of the paper's released sheet modes, whose modal box is
        [-0.625, 0.625]^m).
    """
    if boundary not in ("dirichlet", "free"):
        raise ValueError(f"boundary '{boundary}': use 'dirichlet' or 'free'")
    if normalization not in ("mass", "euclidean"):
        raise ValueError(f"normalization '{normalization}': use 'mass' or 'euclidean'")
    n = potential.n_vertices
    masses = potential.masses.detach().cpu().numpy().astype(np.float64)
    x = np.asarray(x, dtype=np.float64)
    free = np.ones(n, dtype=bool)
    if boundary == "dirichlet":
        free[potential.dirichlet.cpu().numpy()] = False
    free_dofs = np.flatnonzero(np.repeat(free, 3))
    n_rigid = 6 if boundary == "free" else 0
    m = np.repeat(masses, 3)[free_dofs]
    w, V, _ = lowest_modes(potential, k + n_rigid, x, free_dofs, tol=tol)
    if n_rigid:
        R = rigid_modes(x, masses)
        # the six lowest must span the rigid space: their M-projection onto it keeps them whole
        low = V[:, :n_rigid]
        captured = np.linalg.norm(R.T @ (m[:, None] * low), axis=0)
        if not np.all(captured > 1 - 1e-6):
            raise RuntimeError(f"the six lowest modes are not rigid (captured {captured}); is the object connected?")
        w, V = w[n_rigid:], V[:, n_rigid:]
        V = V - R @ (R.T @ (m[:, None] * V))  # deflate the rigid space exactly
        V = V / np.sqrt((m[:, None] * V * V).sum(0))
    if normalization == "euclidean":
        V = V / np.linalg.norm(V, axis=0)
    V = fix_sign(V)
    full = np.zeros((3 * n, k))
    full[free_dofs] = V
    return LinearModes(omega2=w, modes=full, free_dofs=free_dofs, rigid_removed=n_rigid, normalization=normalization)


# --------------------------------------------------------------------------------------------------
# the model
# --------------------------------------------------------------------------------------------------
NM_DEFAULTS = {
    "modes": 3,
    "boundary": "free",
    "normalization": "euclidean",
    "widths": [64, 64, 64, 64],
    "box": 0.625,
    "sampling": "grid",
    "grid": 9,
    "batch_size": 1024,
    "epochs": 200,
    "optimizer": "lbfgs",
    "lr": 1.0,
    "lbfgs_max_iter": 20,
    "lam": 1.0e8,
    "eta": 1.0e7,
    "orthogonality": "paper",
    "metric": "euclidean",
    "exact_origin": True,
    "symmetry": "none",
}


class NeuralModes(nn.Module):
    """n(z) = X + sum_i z_i e_i + y(z, a), y an MLP with GELU activations (paper Eq. 10).

    Parameters
    ----------
    rest_positions : (n,3) X.
    modes : (3n, m) linear modes e_i.
    widths : hidden layer widths (Table 1: the sheet's '5x64' is four hidden
        layers of 64 plus the output layer).
    aux_dim : number of auxiliary inputs (material/shape parameters) after z.
    fixed_dofs : DoFs the correction must leave at rest (Dirichlet), or None.
    rigid, masses : for a free-floating object, the M-orthonormal rigid modes
        R (3n, 6) and the vertex masses; the correction is then projected
        M-orthogonally off span(R), y <- y - R R^T M y (the rigid motion is
        not part of the modal subspace; a dynamics solver adds it separately).
    exact_origin : y(z) = MLP(z) - MLP(0), so n(0) = X exactly (to round-off)
        and the paper's eta ||y(0)||^2 term is identically zero.  False keeps
        the paper's plain MLP, where only that penalty holds y(0) near 0
        (|y(0)| ~ 1e-4 |X| after short trainings).
    exact_orthogonality : None (the paper: the loss's lambda (l^T y)^2 holds
        the constraint), or 'euclidean' / 'mass': y is projected off l(z) in
        that inner product, y <- y - l (l^T W y) / (l^T W l) (W = I or M; needs
        ``masses``), so l^T W y = 0 to round-off (``orthogonality='exact'``).
    symmetry : None, or ``(perm, R, parity)``, a symmetry of order two of the
        scene (``nm_sheet.half_turn``): vertex i goes to vertex perm[i] with
        its displacement rotated by R (3,3), and mode i to parity[i] times
        itself.  The correction is averaged with its image,
        y(z) <- (y(z) + T y(S z)) / 2 with S = diag(parity), so that
        n(S z) = T n(z) holds to round-off (``symmetry='half_turn'``); the
        projections above commute with T, so they keep it.

    The output layer starts at zero, so the untrained map is the linear one.
    Float64 throughout, like the physics.
    """

    def __init__(self, rest_positions, modes, widths=(64, 64, 64, 64), aux_dim: int = 0, fixed_dofs=None, rigid=None, masses=None, exact_origin=True,
                 exact_orthogonality=None, symmetry=None):  # fmt: skip
        super().__init__()
        X = torch.as_tensor(np.asarray(rest_positions), dtype=torch.float64)
        E = torch.as_tensor(np.asarray(modes), dtype=torch.float64)
        self.n, self.m, self.aux_dim = X.shape[0], E.shape[1], int(aux_dim)
        self.exact_origin = bool(exact_origin)
        if exact_orthogonality not in (None, "euclidean", "mass"):
            raise ValueError(f"exact_orthogonality '{exact_orthogonality}': use None, 'euclidean' or 'mass'")
        if exact_orthogonality == "mass" and masses is None:
            raise ValueError("exact_orthogonality 'mass' needs the vertex masses")
        self.exact_orthogonality = exact_orthogonality
        self.hparams = {"n": self.n, "m": self.m, "widths": [int(w) for w in widths], "aux_dim": self.aux_dim, "exact_origin": self.exact_origin,
                        "exact_orthogonality": exact_orthogonality, "symmetry": symmetry is not None}  # fmt: skip
        if exact_orthogonality == "mass":
            self.register_buffer("w3", torch.as_tensor(np.repeat(np.asarray(masses, dtype=np.float64), 3)))
        else:
            self.w3 = None
        self.register_buffer("X", X.reshape(-1))
        self.register_buffer("E", E)
        mask = torch.ones(3 * self.n, dtype=torch.float64)
        if fixed_dofs is not None and len(fixed_dofs):
            mask[torch.as_tensor(np.asarray(fixed_dofs), dtype=torch.long)] = 0.0
        self.register_buffer("mask", mask)
        if rigid is not None:
            R = torch.as_tensor(np.asarray(rigid), dtype=torch.float64)
            m3 = torch.as_tensor(np.repeat(np.asarray(masses, dtype=np.float64), 3))
            self.register_buffer("R", R)
            self.register_buffer("MR", m3[:, None] * R)
        else:
            self.R = self.MR = None
        if symmetry is not None:
            perm, Rs, parity = (np.asarray(a) for a in symmetry)
            if perm.shape != (self.n,) or not np.array_equal(np.sort(perm), np.arange(self.n)) or Rs.shape != (3, 3) or parity.shape != (self.m,):
                raise ValueError(f"symmetry: need a permutation of the {self.n} vertices, a (3,3) rotation and {self.m} mode parities")
            inverse = np.empty_like(perm)
            inverse[perm] = np.arange(self.n)
            self.register_buffer("sym_source", torch.as_tensor(inverse, dtype=torch.long))  # image[j] = R u[sym_source[j]]
            self.register_buffer("sym_R", torch.as_tensor(Rs, dtype=torch.float64))
            self.register_buffer("sym_parity", torch.as_tensor(parity, dtype=torch.float64))
        else:
            self.sym_source = self.sym_R = self.sym_parity = None
        layers, prev = [], self.m + self.aux_dim
        for w in widths:
            layers += [nn.Linear(prev, int(w), dtype=torch.float64), nn.GELU()]
            prev = int(w)
        out = nn.Linear(prev, 3 * self.n, dtype=torch.float64)
        nn.init.zeros_(out.weight)
        nn.init.zeros_(out.bias)
        self.mlp = nn.Sequential(*layers, out)

    def linear(self, z: torch.Tensor) -> torch.Tensor:
        """l = sum_i z_i e_i; z (..., m) -> (..., 3n)."""
        return z[..., : self.m].to(self.E.dtype) @ self.E.T

    def _network(self, z: torch.Tensor, aux: torch.Tensor | None) -> torch.Tensor:
        h = z if aux is None else torch.cat([z, aux.to(z.dtype)], -1)
        y = self.mlp(h)
        if self.exact_origin:
            h0 = z.new_zeros(self.m) if aux is None else torch.cat([torch.zeros_like(z), aux.to(z.dtype)], -1)
            y = y - self.mlp(h0)
        return y

    def turn(self, u: torch.Tensor) -> torch.Tensor:
        """The symmetry's image T u of displacements u (..., 3n)."""
        v = u.reshape(u.shape[:-1] + (self.n, 3)) @ self.sym_R.T
        return v.index_select(-2, self.sym_source).reshape(u.shape)

    def correction(self, z: torch.Tensor, aux: torch.Tensor | None = None) -> torch.Tensor:
        """y(z, a); (..., m) [, (..., aux_dim)] -> (..., 3n), zero on fixed DoFs."""
        z = z.to(self.E.dtype)
        y = self._network(z, aux)
        if self.sym_R is not None:
            even = bool(torch.all(self.sym_parity > 0))
            y = 0.5 * (y + self.turn(y if even else self._network(z * self.sym_parity, aux)))
        y = y * self.mask
        if self.R is not None:
            y = y - (y @ self.MR) @ self.R.T
        if self.exact_orthogonality is not None:
            # off l in the constraint's inner product (l is M-orthogonal to the rigid modes and zero on
            # fixed DoFs, so neither property above is undone); z = 0 (l = 0) keeps y
            l = self.linear(z)
            wl = l if self.w3 is None else l * self.w3
            ll = (wl * l).sum(-1, keepdim=True)
            y = y - l * torch.where(ll > 0, (wl * y).sum(-1, keepdim=True) / torch.where(ll > 0, ll, 1.0), 0.0)
        return y

    def forward(self, z: torch.Tensor, aux: torch.Tensor | None = None) -> torch.Tensor:
        """n(z): positions (..., n, 3)."""
        u = self.linear(z) + self.correction(z, aux)
        return (self.X + u).reshape(z.shape[:-1] + (self.n, 3))


def load_neural_modes(path) -> NeuralModes:
    """A :class:`NeuralModes` saved by ``latent.save_module`` (rule nm_train), in eval mode."""
    blob = torch.load(path, map_location="cpu", weights_only=True)
    if blob.get("kind") != "NeuralModes":
        raise ValueError(f"{path} holds a {blob.get('kind')!r}, not NeuralModes")
    return neural_modes_from_state(blob["hparams"], blob["state_dict"]).eval()


def neural_modes_from_state(hp: dict, sd: dict) -> NeuralModes:
    """A :class:`NeuralModes` rebuilt from its ``hparams`` and ``state_dict`` (every buffer is in the state dict)."""
    rigid = sd.get("R")
    symmetry = None
    if hp.get("symmetry"):  # placeholders of the right shapes: the state dict holds the symmetry
        symmetry = (np.arange(hp["n"]), np.eye(3), np.ones(hp["m"]))
    model = NeuralModes(
        sd["X"].reshape(-1, 3).numpy(),
        sd["E"].numpy(),
        hp["widths"],
        hp["aux_dim"],
        fixed_dofs=np.flatnonzero(sd["mask"].numpy() == 0),
        rigid=None if rigid is None else rigid.numpy(),
        masses=None if rigid is None and hp.get("exact_orthogonality") != "mass" else np.ones(hp["n"]),  # MR, w3: from the state dict
        exact_origin=hp["exact_origin"],
        exact_orthogonality=hp.get("exact_orthogonality"),
        symmetry=symmetry,
    )
    model.load_state_dict(sd)
    return model


def from_config(basis: dict, cfg: dict, masses=None, aux_dim: int = 0, symmetry=None) -> NeuralModes:
    """An untrained :class:`NeuralModes` for settings ``cfg`` (``NM_DEFAULTS`` keys: widths, exact_origin,
    orthogonality, metric, symmetry) on ``basis`` (X, modes, fixed_dofs, rigid: ``nm_pipeline.read_linear_modes``).

    ``cfg['symmetry']`` 'half_turn' builds ``symmetry`` (``nm_sheet.half_turn`` of the scene; required then)
    into the map; 'none' leaves the map free to break it.
    """
    cfg = {**NM_DEFAULTS, **cfg}
    if cfg["symmetry"] not in ("none", "half_turn"):
        raise ValueError(f"neural_modes.symmetry '{cfg['symmetry']}': use 'none' or 'half_turn'")
    if cfg["symmetry"] == "half_turn" and symmetry is None:
        raise ValueError("neural_modes.symmetry 'half_turn': the scene has no half-turn symmetry (mesh, fixed DoFs and modes must map onto themselves)")
    return NeuralModes(
        basis["X"], basis["modes"], cfg["widths"], aux_dim, fixed_dofs=basis["fixed_dofs"], rigid=basis.get("rigid"), masses=masses,
        exact_origin=cfg["exact_origin"], exact_orthogonality=cfg["metric"] if cfg["orthogonality"] == "exact" else None,
        symmetry=symmetry if cfg["symmetry"] == "half_turn" else None,
    )  # fmt: skip


def neural_modes_loss(model: NeuralModes, potential: IncrementalPotential, z, aux=None, lam=1e8, eta=1e7, orthogonality="paper", metric="euclidean"):
    """Paper Eq. 12-13; returns (loss, parts) with parts = mean energy, mean constraint, origin term.

    ``metric='mass'`` uses l^T M y in place of l^T y (see ``ConstrainedNewton``).
    """
    l = model.linear(z)
    y = model.correction(z, aux)
    x = (model.X + l + y).reshape(z.shape[:-1] + (model.n, 3))
    energy = potential.elastic(x)
    if metric == "mass":
        c = (l * potential.masses.repeat_interleave(3).to(l) * y).sum(-1)
    elif metric == "euclidean":
        c = (l * y).sum(-1)
    else:
        raise ValueError(f"metric '{metric}': use 'euclidean' or 'mass'")
    if orthogonality == "unit":
        c = c / l.norm(dim=-1).clamp_min(1e-12)
    elif orthogonality == "exact":
        if model.exact_orthogonality != metric:
            raise ValueError(f"orthogonality 'exact' needs a NeuralModes built with exact_orthogonality='{metric}' (see from_config)")
    elif orthogonality != "paper":
        raise ValueError(f"orthogonality '{orthogonality}': use 'paper', 'unit' or 'exact'")
    z0 = torch.zeros((1, model.m), dtype=z.dtype)
    a0 = None if aux is None else aux[:1]
    y0 = model.correction(z0, a0)
    origin = (y0 * y0).sum()
    loss = energy.mean() + lam * (c * c).mean() + eta * origin
    return loss, {"energy": energy.mean().detach(), "constraint": (c * c).mean().detach(), "origin": origin.detach()}


def modal_samples(kind: str, m: int, box: float, count: int = 0, resolution: int = 9, generator=None) -> torch.Tensor:
    """Modal coordinates: a regular ``resolution``^m grid over [-box, box]^m, or ``count`` uniform samples."""
    if kind == "grid":
        axis = np.linspace(-box, box, resolution)
        return torch.as_tensor(np.array(list(itertools.product(axis, repeat=m))), dtype=torch.float64)
    if kind in ("stochastic", "uniform"):
        return (torch.rand(count, m, generator=generator, dtype=torch.float64) * 2 - 1) * box
    raise ValueError(f"sampling '{kind}': use 'grid' or 'stochastic'")


def make_optimizer(params, cfg: dict):
    """``cfg['optimizer']``: 'lbfgs' (strong-Wolfe line search, up to ``lbfgs_max_iter`` iterations a step, as the
    paper) or 'adam'; learning rate ``lr``."""
    if cfg["optimizer"] == "lbfgs":
        return torch.optim.LBFGS(params, lr=float(cfg["lr"]), max_iter=int(cfg["lbfgs_max_iter"]), line_search_fn="strong_wolfe")
    if cfg["optimizer"] == "adam":
        return torch.optim.Adam(params, lr=float(cfg["lr"]))
    raise ValueError(f"optimizer '{cfg['optimizer']}': use 'lbfgs' or 'adam'")


def optimizer_step(opt, closure) -> None:
    """One epoch's step: L-BFGS evaluates ``closure`` itself (several times); Adam steps after one evaluation."""
    if isinstance(opt, torch.optim.LBFGS):
        opt.step(closure)
    else:
        closure()
        opt.step()


def train_neural_modes(model: NeuralModes, potential: IncrementalPotential, config: dict | None = None, seed: int = 0, callback=None, compiled: bool = True):
    """Train Neural Modes self-supervised (Eq. 13).

    config keys (``NM_DEFAULTS``): sampling ('grid' | 'stochastic'), grid,
    batch_size, box, epochs, optimizer ('lbfgs' with strong-Wolfe line search,
    as the paper, or 'adam'), lr, lbfgs_max_iter, lam, eta, orthogonality, metric.
    One epoch = one optimiser step (L-BFGS: up to ``lbfgs_max_iter``
    iterations) on one batch; stochastic sampling draws a new batch each epoch.
    ``callback(epoch, model)`` runs after every epoch.  ``compiled``: the loss's
    elastic energy runs the simulator's compiled kernels on the CPU
    (``energy.kernels.with_compiled_elastic``: the same formulas, several times
    faster than the batched PyTorch energy under autograd).

    Returns history: dict of per-epoch lists (loss, energy, constraint, origin) and seconds.
    """
    cfg = {**NM_DEFAULTS, **(config or {})}
    if compiled:
        potential = with_compiled_elastic(potential)
    gen = torch.Generator().manual_seed(seed)
    opt = make_optimizer([p for p in model.parameters() if p.requires_grad], cfg)
    grid = modal_samples("grid", model.m, cfg["box"], resolution=int(cfg["grid"])) if cfg["sampling"] == "grid" else None
    hist = {"loss": [], "energy": [], "constraint": [], "origin": []}
    t0 = time.perf_counter()
    for epoch in range(int(cfg["epochs"])):
        z = grid if grid is not None else modal_samples("stochastic", model.m, cfg["box"], int(cfg["batch_size"]), generator=gen)
        parts = {}

        def closure(z=z, parts=parts):
            opt.zero_grad()
            loss, p = neural_modes_loss(model, potential, z, None, cfg["lam"], cfg["eta"], cfg["orthogonality"], cfg["metric"])
            loss.backward()
            parts.update(p, loss=loss.detach())
            return loss

        optimizer_step(opt, closure)
        for key, values in hist.items():
            values.append(float(parts[key]))
        if not np.isfinite(hist["loss"][-1]):
            raise FloatingPointError(f"Neural Modes training diverged at epoch {epoch + 1}")
        if callback is not None:
            callback(epoch, model)
    hist["seconds"] = time.perf_counter() - t0
    return hist


# --------------------------------------------------------------------------------------------------
# ground truth: nonlinear compliant modes (Eq. 9)
# --------------------------------------------------------------------------------------------------
def ground_truth(
    potential, rest_positions, modes, z, free_dofs=None, rigid=None, metric="euclidean", rtol=1e-5, etol=1e-7, max_iter=60, progress=None
):
    """Eq. 9 for every row of z (N, m): positions (N, n, 3), energies (N,), infos.

    Each sample starts from the lower-energy of X + l and the previous
    sample's correction made feasible (grids are visited in order, so the
    previous sample is usually a neighbour).
    """
    solver = ConstrainedNewton(potential, rest_positions, free_dofs, rigid, metric)
    E = np.asarray(modes, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    X = solver.X.reshape(-1)
    out, infos = np.empty((len(z), len(X))), []
    y_prev = None
    for i, zi in enumerate(z):
        l = E @ zi
        y0 = None
        if y_prev is not None and solver.energy(X + l + y_prev) < solver.energy(X + l):
            y0 = y_prev  # made feasible by solve()
        x, info = solver.solve(l, y0, rtol=rtol, etol=etol, max_iter=max_iter)
        out[i] = x
        infos.append(info)
        y_prev = x - X - l
        if progress is not None:
            progress(i, info)
    return out.reshape(len(z), -1, 3), np.array([i.energy for i in infos]), infos


# --------------------------------------------------------------------------------------------------
# latent directions at the origin (mode collapse, Fig. 4)
# --------------------------------------------------------------------------------------------------
def latent_directions(decoder, m: int) -> torch.Tensor:
    """Jacobian (3n, m) of z -> x (flattened) at z = 0; ``decoder`` maps (1, m) -> (1, n, 3)."""
    z0 = torch.zeros(1, m, dtype=torch.float64)
    J = torch.autograd.functional.jacobian(lambda z: decoder(z).reshape(-1), z0)
    return J.reshape(-1, m).detach()


def direction_correlation(J, masses) -> tuple[np.ndarray, np.ndarray]:
    """Normalised mass-weighted Gram matrix C_ij = <J_i, J_j>_M / (|J_i|_M |J_j|_M) and its eigenvalues (descending)."""
    J = np.asarray(J, dtype=np.float64)
    m3 = np.repeat(np.asarray(masses, dtype=np.float64), 3)
    G = J.T @ (m3[:, None] * J)
    d = np.sqrt(np.clip(np.diag(G), 1e-300, None))
    C = G / np.outer(d, d)
    return C, np.sort(np.linalg.eigvalsh(C))[::-1]

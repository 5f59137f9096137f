r"""Neural Modes conditioned on a shape parameter: a sheet's aspect ratio (Wang et al. 2024, Sec. 4.3, Fig. A2).

The paper adds the edge-length ratio of a rectangular sheet as one auxiliary input of the MLP (Table 1:
"Sheet (aspect ratio)", 4 modes, 1 auxiliary input, 8x64) and shows the first mode's folding direction
turning smoothly from the short axis (2:1) to the diagonal (1:1).  Here:

Shapes.  The scene's sheet, rest positions X, is stretched about its centroid along its longer in-plane
axis by sqrt(r / r0) and along the shorter one by sqrt(r0 / r) (r0 the mesh's own ratio), so the edge
ratio is r and every triangle keeps its area (hence the lumped masses).  Each ratio has its own rest
shape, potential (the same energy implementation as everywhere, built on the stretched rest state) and
linear modes.

Mode family.  The m lowest modes are computed at every ratio of a grid, largest first, and *tracked*:
at each next ratio the m + ``extra`` lowest are matched to the previous ratio's modes by largest
overlap (an assignment problem) and their signs aligned, so mode i is one continuous family in r even
where two modes swap their frequency order (more modes are computed where a tracked one has climbed
out of the m + extra lowest).  The smallest overlap between neighbours is recorded;
a small one means the grid is too coarse to follow the modes.

Network.  One MLP y(z, r) (aux_dim = 1) shared by one :class:`~latentsim.neural_modes.network.NeuralModes` per
ratio (rest shape, modes, rigid modes, symmetry of that ratio), so

    n(z, r) = X(r) + sum_i z_i e_i(r) + y(z, r),

trained by Eq. 13 averaged over the training ratios (each a fresh uniform batch every epoch).
Held-out ratios (between the training ones) test that the network generalises in r.

Evaluation.  At every ratio: mean energy of Neural Modes, of the linear modes and of the ground truth
(Eq. 9 solved at that ratio) on the same uniform test samples; the energy when the network is given
the wrong ratio (the other end of the range), which would equal the right one if the auxiliary input
were ignored; and the folding direction of the first mode (:func:`fold_angle`) at half the box.
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from torch import nn
from tqdm import tqdm

from latentsim.config import with_defaults
from latentsim.latent.serialization import load_blob
from latentsim.neural_modes.compliant_modes import ground_truth
from latentsim.neural_modes.linear import fixed_dofs, linear_modes, rigid_modes
from latentsim.neural_modes.network import NeuralModes, from_config, neural_modes_from_state
from latentsim.neural_modes.symmetry import half_turn
from latentsim.neural_modes.training import make_optimizer, modal_samples, neural_modes_loss
from latentsim.physics.kernels import with_compiled_elastic
from latentsim.scene import build_elastic

log = logging.getLogger(__name__)

__all__ = ["ModeFamily", "RatioConditionedModes", "evaluate_family", "fold_angle", "load_family_model", "mode_family", "sheet_axes", "stretched", "train_family"]


def sheet_axes(X) -> tuple[int, int, int]:
    """(long, short, normal) coordinate axes of a flat sheet, by extent (ties keep the axis order)."""
    X = np.asarray(X, dtype=np.float64)
    ext = np.ptp(X, axis=0)
    long, short, normal = (int(a) for a in np.argsort(-ext, kind="stable"))
    if ext[normal] > 1e-6 * ext[long]:
        raise ValueError(f"the aspect-ratio study needs a flat sheet in a coordinate plane; extents {ext}")
    return long, short, normal


def stretched(X, ratio: float) -> np.ndarray:
    """X stretched about its centroid to edge ratio ``ratio`` (long : short), keeping every area."""
    X = np.asarray(X, dtype=np.float64)
    if not ratio > 0:
        raise ValueError(f"aspect ratio {ratio}: must be positive")
    long, short, _ = sheet_axes(X)
    ext = np.ptp(X, axis=0)
    s = np.sqrt(ratio / (ext[long] / ext[short]))
    c = X.mean(0)
    Y = X.copy()
    Y[:, long] = c[long] + s * (X[:, long] - c[long])
    Y[:, short] = c[short] + (X[:, short] - c[short]) / s
    return Y


def fold_angle(X, u) -> float:
    """Folding direction of a displacement field u (n,3) of the sheet X (n,3), in degrees in [0, 90].

    The normal displacement is fitted by a quadratic in the in-plane coordinates; the angle is between
    the long axis and the principal direction of the fit's larger |curvature|: 0 bends the long axis
    (the fold line runs along the short axis), 90 bends the short axis, 45 folds along a diagonal (a
    twist, w ~ xy, has equal and opposite curvatures at +-45 degrees).
    """
    X = np.asarray(X, dtype=np.float64)
    long, short, normal = sheet_axes(X)
    P = X - X.mean(0)
    a, b = P[:, long], P[:, short]
    w = np.asarray(u, dtype=np.float64).reshape(-1, 3)[:, normal]
    A = np.column_stack([a * a, a * b, b * b, a, b, np.ones_like(a)])
    co = np.linalg.lstsq(A, w, rcond=None)[0]
    ev, V = np.linalg.eigh(np.array([[2 * co[0], co[1]], [co[1], 2 * co[2]]]))
    v = V[:, int(np.argmax(np.abs(ev)))]
    angle = np.degrees(np.arctan2(abs(v[1]), abs(v[0])))
    return float(angle)


# --------------------------------------------------------------------------------------------------
# linear modes along the ratio
# --------------------------------------------------------------------------------------------------
@dataclass
class ModeFamily:
    """Tracked linear modes of a stretched sheet at each ratio (see the module docstring).

    ratios (K,), X (K,n,3), modes (K,3n,m), omega2 (K,m), overlap (K,) (|cos| of each mode with its
    match at the previous ratio, smallest of the m; 1 at the first), rank (K,m) (each tracked mode's
    place in its ratio's frequency order), fixed_dofs, rigid (K,3n,6) or None, masses (n,).
    """

    ratios: np.ndarray
    X: np.ndarray
    modes: np.ndarray
    omega2: np.ndarray
    overlap: np.ndarray
    rank: np.ndarray
    fixed_dofs: np.ndarray
    rigid: np.ndarray | None
    masses: np.ndarray

    def basis(self, k: int) -> dict:
        """Ratio k's basis in ``stages.neural_modes.read_linear_modes`` form."""
        return {"X": self.X[k], "modes": self.modes[k], "fixed_dofs": self.fixed_dofs, "rigid": None if self.rigid is None else self.rigid[k],
                "masses": self.masses}  # fmt: skip


def ratio_potential(arrays: dict, model: str, material: dict, X):
    """The elastic potential of the scene's mesh on rest positions X (no inertia or gravity needed)."""
    return build_elastic(model, {**arrays, "rest_positions": np.asarray(X)}, material)


def mode_family(arrays: dict, model: str, material: dict, ratios, m: int, boundary: str = "free", normalization: str = "euclidean", extra: int = 2):
    """Tracked linear modes of the sheet ``arrays`` stretched to each of ``ratios`` (the largest first)."""
    if model != "shell":
        raise ValueError(f"the aspect-ratio study stretches a sheet: model '{model}' is not 'shell'")
    ratios = np.asarray(ratios, dtype=np.float64)
    X0 = np.asarray(arrays["rest_positions"], dtype=np.float64)
    n = len(X0)
    K = len(ratios)
    X, modes, omega2 = np.empty((K, n, 3)), np.empty((K, 3 * n, m)), np.empty((K, m))
    overlap, rank = np.ones(K), np.empty((K, m), dtype=np.int64)
    rigid = np.empty((K, 3 * n, 6)) if boundary == "free" else None
    masses = prev = None
    for k in np.argsort(-ratios, kind="stable"):
        X[k] = stretched(X0, ratios[k])
        pot = ratio_potential(arrays, model, material, X[k])
        if prev is None:
            lm = linear_modes(pot, m, X[k], boundary=boundary, normalization=normalization)
            pick, signs = np.arange(m), np.ones(m)
        else:
            more = extra
            while True:  # a tracked mode may have left the m + extra lowest: look further up
                lm = linear_modes(pot, m + more, X[k], boundary=boundary, normalization=normalization)
                unit = lm.modes / np.linalg.norm(lm.modes, axis=0)
                cos = (prev / np.linalg.norm(prev, axis=0)).T @ unit  # (m, m + more)
                rows, pick = linear_sum_assignment(-np.abs(cos))
                if np.abs(cos[rows, pick]).min() >= 0.7 or more >= 4 * m + 8:
                    break
                more = 2 * more + m
            signs = np.sign(cos[rows, pick])
            overlap[k] = np.abs(cos[rows, pick]).min()
        V = lm.modes
        modes[k] = V[:, pick] * signs
        omega2[k] = lm.omega2[pick]
        rank[k] = pick
        prev = modes[k]
        masses = pot.masses.numpy().astype(np.float64)
        if rigid is not None:
            rigid[k] = rigid_modes(X[k], masses)
    fixed = fixed_dofs(arrays["dirichlet"], boundary)
    return ModeFamily(ratios, X, modes, omega2, overlap, rank, fixed, rigid, masses)


# --------------------------------------------------------------------------------------------------
# the conditioned network
# --------------------------------------------------------------------------------------------------
class RatioConditionedModes(nn.Module):
    """One :class:`NeuralModes` per ratio of a :class:`ModeFamily`, all sharing one MLP y(z, r).

    ``member(k)`` is ratio k's map; ``forward(z, k)`` its positions with the auxiliary input r_k (or
    ``ratio``, to feed the network another ratio than the shape's).
    """

    def __init__(self, members, ratios):
        super().__init__()
        if len(members) != len(ratios):
            raise ValueError(f"{len(members)} members for {len(ratios)} ratios")
        self.members = nn.ModuleList(members)
        for other in self.members[1:]:
            other.mlp = self.members[0].mlp
        self.m = self.members[0].m
        self.ratios = [float(r) for r in ratios]
        self.hparams = {"members": [mem.hparams for mem in self.members], "ratios": self.ratios}

    @classmethod
    def build(cls, family: ModeFamily, cfg: dict, cells, symmetric: bool):
        """Untrained members from :func:`~latentsim.neural_modes.network.from_config` (``cfg``: the
        schema's ``neural_modes`` keys), aux_dim 1."""
        members = []
        for k, r in enumerate(family.ratios):
            basis = family.basis(k)
            sym = half_turn(basis["X"], cells, basis["modes"], basis["fixed_dofs"]) if symmetric else None
            if symmetric and sym is None:
                raise ValueError(f"neural_modes.symmetry 'half_turn': the sheet at ratio {r:g} has no half-turn symmetry of its modes")
            members.append(from_config(basis, cfg, family.masses, aux_dim=1, symmetry=sym))
        return cls(members, family.ratios)

    @classmethod
    def from_state(cls, hparams: dict, state_dict: dict):
        members = []
        for k, hp in enumerate(hparams["members"]):
            prefix = f"members.{k}."
            sd = {key[len(prefix):]: v for key, v in state_dict.items() if key.startswith(prefix)}
            members.append(neural_modes_from_state(hp, sd))
        model = cls(members, hparams["ratios"])
        model.load_state_dict(state_dict)
        return model

    def member(self, k: int) -> NeuralModes:
        return self.members[k]

    def forward(self, z: torch.Tensor, k: int, ratio: float | None = None) -> torch.Tensor:
        """Positions (..., n, 3) of ratio k's shape at z; the network is told ``ratio`` (default r_k)."""
        return self.members[k](z, aux_of(z, self.ratios[k] if ratio is None else ratio))


def aux_of(z: torch.Tensor, ratio: float) -> torch.Tensor:
    """The auxiliary input (N, 1) of a batch of modal coordinates z (N, m)."""
    return torch.full(z.shape[:-1] + (1,), float(ratio), dtype=torch.float64)


def train_family(model: RatioConditionedModes, potentials: dict, cfg: dict, batch_size: int, epochs: int, seed: int = 0, progress: bool = False):
    """Eq. 13 averaged over the training ratios: ``potentials`` {k: potential of ratio k} for each training k.

    L-BFGS (strong Wolfe) or Adam as ``cfg['optimizer']``; every epoch draws a fresh uniform batch of
    ``batch_size`` modal samples per training ratio.  Returns the history (loss, energy, constraint per
    epoch; seconds).
    """
    cfg = with_defaults("neural_modes", cfg, "train_family")
    pots = {k: with_compiled_elastic(p) for k, p in potentials.items()}
    gen = torch.Generator().manual_seed(seed)
    opt = make_optimizer(list(model.parameters()), cfg)
    hist = {"loss": [], "energy": [], "constraint": []}
    t0 = time.perf_counter()
    for epoch in tqdm(range(int(epochs)), desc="aspect-ratio Neural Modes", disable=not progress, file=sys.stderr, leave=False):
        zs = {k: modal_samples("stochastic", model.m, cfg["box"], int(batch_size), generator=gen) for k in pots}
        parts = {}

        def closure(zs=zs, parts=parts):
            opt.zero_grad()
            total, energy, constraint = 0.0, 0.0, 0.0
            for k, z in zs.items():
                loss, p = neural_modes_loss(model.member(k), pots[k], z, aux_of(z, model.ratios[k]), cfg["lam"], cfg["eta"], cfg["orthogonality"], cfg["metric"])
                total = total + loss / len(zs)
                energy += float(p["energy"]) / len(zs)
                constraint += float(p["constraint"]) / len(zs)
            total.backward()
            parts.update(loss=float(total.detach()), energy=energy, constraint=constraint)
            return total

        opt.step(closure)  # L-BFGS evaluates the closure itself; Adam once before its step
        for key, values in hist.items():
            values.append(parts[key])
        if not np.isfinite(hist["loss"][-1]):
            raise FloatingPointError(f"aspect-ratio Neural Modes training diverged at epoch {epoch + 1}")
    hist["seconds"] = time.perf_counter() - t0
    return hist


def evaluate_family(model: RatioConditionedModes, family: ModeFamily, potentials: dict, z, train_mask, cfg: dict, max_iter: int = 40,
                    amplitude: float = 0.5, progress: bool = False) -> dict:  # fmt: skip
    """Every ratio's energies on the test samples z (N,m), with and without the right auxiliary input,
    the ground truth of Eq. 9, and the first mode's folding direction; arrays over ratios (K,), and
    ``modes_plus`` (K,m,n,3): each mode decoded at z_i = ``amplitude`` * ``cfg['box']`` (the fold is measured there)."""
    cfg = with_defaults("neural_modes", cfg, "evaluate_family")
    box = float(cfg["box"])
    ratios = family.ratios
    K, m = len(ratios), model.m
    zt = torch.as_tensor(np.asarray(z, dtype=np.float64))
    lo, hi = float(ratios.min()), float(ratios.max())
    out = {key: np.empty(K) for key in ("E_gt", "E_nm", "E_linear", "E_wrong_ratio", "dE_nm", "dE_linear", "fold_nm", "fold_linear", "gt_residual_max",
                                        "constraint_max")}  # fmt: skip
    modes_plus = np.empty((K, m) + family.X.shape[1:])  # each mode at z_i = amplitude * box, decoded
    gt_seconds = 0.0
    n = family.X.shape[1]
    free = np.setdiff1d(np.arange(3 * n), family.fixed_dofs)
    for k in tqdm(range(K), desc="aspect ratios", disable=not progress, file=sys.stderr, leave=False):
        pot, mem, r = potentials[k], model.member(k), float(ratios[k])
        wrong = hi if r < 0.5 * (lo + hi) else lo
        with torch.no_grad():
            x_nm = model(zt, k)
            x_wrong = model(zt, k, ratio=wrong)
            l = mem.linear(zt)
            x_lin = (mem.X + l).reshape(-1, n, 3)
            y = x_nm.reshape(len(zt), -1) - mem.X - l
            cons = ((l * y).sum(-1).abs() / (l.norm(dim=-1) * y.norm(dim=-1)).clamp_min(1e-300)).max()
            e_nm, e_lin, e_wrong = (pot.elastic(x).numpy() for x in (x_nm, x_lin, x_wrong))
            zi = torch.as_tensor(amplitude * box * np.eye(m))
            modes_plus[k] = model(zi, k).numpy()
        t0 = time.perf_counter()
        _, e_gt, infos = ground_truth(pot, family.X[k], family.modes[k], z, free_dofs=free, rigid=None if family.rigid is None else family.rigid[k],
                                         metric=cfg["metric"], max_iter=max_iter)  # fmt: skip
        gt_seconds += time.perf_counter() - t0
        out["E_gt"][k], out["E_nm"][k], out["E_linear"][k], out["E_wrong_ratio"][k] = e_gt.mean(), e_nm.mean(), e_lin.mean(), e_wrong.mean()
        out["dE_nm"][k], out["dE_linear"][k] = np.abs(e_nm - e_gt).mean(), np.abs(e_lin - e_gt).mean()
        out["fold_nm"][k] = fold_angle(family.X[k], modes_plus[k, 0] - family.X[k])
        out["fold_linear"][k] = fold_angle(family.X[k], family.modes[k][:, 0].reshape(-1, 3))
        out["gt_residual_max"][k] = max(i.residual for i in infos)
        out["constraint_max"][k] = float(cons)
        log.info("ratio %.3g (%s): E gt %.4g, NM %.4g, linear %.4g, wrong ratio %.4g; fold NM %.1f deg, linear %.1f deg", r,
                 "train" if train_mask[k] else "held out", out["E_gt"][k], out["E_nm"][k], out["E_linear"][k], out["E_wrong_ratio"][k],
                 out["fold_nm"][k], out["fold_linear"][k])  # fmt: skip
    out["modes_plus"] = modes_plus
    out["gt_seconds"] = gt_seconds
    return out


def load_family_model(path) -> RatioConditionedModes:
    """A :class:`RatioConditionedModes` saved by ``latent.save_module`` (rule nm_aspect_ratio), in eval mode."""
    blob = load_blob(path, "RatioConditionedModes")
    return RatioConditionedModes.from_state(blob["hparams"], blob["state_dict"]).eval()

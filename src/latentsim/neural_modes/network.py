r"""The Neural Modes map (Wang et al. 2024, Eq. 10-11) and its construction from settings and from disk.

For modal coordinates z (m,) and optional auxiliary inputs a (material/shape parameters),

    n(z) = X + l(z) + y(z),    l(z) = sum_i z_i e_i,    y = MLP(z, a)  (GELU).

The correction y can have properties built into the map rather than trained: n(0) = X exactly
(``exact_origin``), zero on the fixed DoFs, M-orthogonal to the rigid modes (free-floating objects),
l^T y = 0 to round-off (``orthogonality='exact'``: y <- y - l (l^T y) / (l^T l), or l^T M y and
l^T M l with ``metric='mass'``), and a half-turn symmetry of the scene (``symmetry='half_turn'``).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from latentsim.config import with_defaults
from latentsim.latent.serialization import load_blob

__all__ = ["NeuralModes", "from_config", "load_neural_modes", "neural_modes_from_state"]


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
        scene (``symmetry.half_turn``): vertex i goes to vertex perm[i] with
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
    blob = load_blob(path, "NeuralModes")
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
    """An untrained :class:`NeuralModes` for settings ``cfg`` (keys of the config schema's ``neural_modes``;
    read: widths, exact_origin, orthogonality, metric, symmetry; the rest from the schema's defaults) on
    ``basis`` (X, modes, fixed_dofs, rigid: ``stages.neural_modes.read_linear_modes``).

    ``cfg['symmetry']`` 'half_turn' builds ``symmetry`` (``symmetry.half_turn`` of the scene; required then)
    into the map; 'none' leaves the map free to break it.
    """
    cfg = with_defaults("neural_modes", cfg, "from_config")
    if cfg["symmetry"] not in ("none", "half_turn"):
        raise ValueError(f"neural_modes.symmetry '{cfg['symmetry']}': use 'none' or 'half_turn'")
    if cfg["symmetry"] == "half_turn" and symmetry is None:
        raise ValueError("neural_modes.symmetry 'half_turn': the scene has no half-turn symmetry (mesh, fixed DoFs and modes must map onto themselves)")
    return NeuralModes(
        basis["X"], basis["modes"], cfg["widths"], aux_dim, fixed_dofs=basis["fixed_dofs"], rigid=basis.get("rigid"), masses=masses,
        exact_origin=cfg["exact_origin"], exact_orthogonality=cfg["metric"] if cfg["orthogonality"] == "exact" else None,
        symmetry=symmetry if cfg["symmetry"] == "half_turn" else None,
    )  # fmt: skip

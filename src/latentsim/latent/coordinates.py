"""Relative coordinates: full positions <-> the vector the autoencoder sees (Li et al. 2025, sec. 3.2).

Positions are written relative to the Dirichlet boundary conditions: root-relative for rods,
relative to the mean prescribed position for cloth and solids (or, ``hard_mean``, the free
vertices only, for bodies that are mostly prescribed).  :func:`coordinates_for` picks a scene's
coordinates from its trajectories file.
"""

from __future__ import annotations

import torch


class RelativeCoordinates:
    """Full positions <-> the vector the autoencoder sees (paper sec. 3.2).

    Modes
    -----
    ``"roots"`` (rods): every free vertex is written relative to its rod's root
        vertex, ``u_i = x_i - x*_{root(i)}``.  The Dirichlet vertices are left
        out of ``u`` and re-applied from their prescribed positions on decode,
        so boundary conditions hold exactly (``hard_dirichlet = True``).
    ``"mean"`` (cloth, solids): every vertex (Dirichlet ones included) is
        written relative to the mean prescribed Dirichlet position,
        ``u_i = x_i - mean_j x*_j``.  Decoded Dirichlet vertices are *not*
        overwritten (``hard_dirichlet = False``): the loss enforces them by the
        quadratic penalty.  With no Dirichlet vertex the origin is 0.
    ``"hard_mean"`` (solids mostly prescribed, e.g. ears on a rigid head): the
        free vertices relative to the mean prescribed position, the Dirichlet
        vertices left out of ``u`` and re-applied on decode
        (``hard_dirichlet = True``).  With the paper's ``"mean"`` encoding such a
        scene's latent must carry the prescribed majority, held only by the
        stiff penalty, and its loss is dominated by it.

    The origin is always taken from the prescribed positions ``xD`` (m, 3) of
    the Dirichlet vertices (which the simulator imposes exactly), so
    ``decode(encode(x, xD), xD) == x`` whenever ``x[dirichlet] == xD``.

    Parameters
    ----------
    n_vertices : number of vertices n.
    dirichlet : (m,) indices of the Dirichlet vertices (order of ``xD``).
    mode : ``"roots"`` or ``"mean"``.
    root_of : (n,) index of each vertex's root vertex (``"roots"`` mode only);
        every root must be a Dirichlet vertex.

    Attributes
    ----------
    dim : length d of the encoded vector.
    encoded_vertices : (n_enc,) vertex indices present in the encoded vector.
    """

    def __init__(self, n_vertices: int, dirichlet, mode: str = "mean", root_of=None):
        self.n = int(n_vertices)
        self.dirichlet = torch.as_tensor(dirichlet, dtype=torch.long).reshape(-1).cpu()
        if mode not in ("roots", "mean", "hard_mean"):
            raise ValueError(f"RelativeCoordinates mode must be 'roots', 'mean' or 'hard_mean', got {mode!r}")
        self.mode = mode
        m = self.dirichlet.numel()
        if m and (self.dirichlet.min() < 0 or self.dirichlet.max() >= self.n):
            raise ValueError("dirichlet indices out of range")
        if mode == "roots":
            if root_of is None:
                raise ValueError("mode 'roots' needs a per-vertex root_of index array")
            root_of = torch.as_tensor(root_of, dtype=torch.long).reshape(-1).cpu()
            if root_of.numel() != self.n:
                raise ValueError(f"root_of has {root_of.numel()} entries, expected {self.n}")
            # position of each vertex's root within the Dirichlet list
            slot = torch.full((self.n,), -1, dtype=torch.long)
            slot[self.dirichlet] = torch.arange(m)
            root_slot = slot[root_of]
            if (root_slot < 0).any():
                raise ValueError("every root in root_of must be a Dirichlet vertex")
            is_d = torch.zeros(self.n, dtype=torch.bool)
            is_d[self.dirichlet] = True
            self.free = torch.nonzero(~is_d).reshape(-1)
            self.root_slot = root_slot[self.free]  # (n_free,)
            self.encoded_vertices = self.free
            self.hard_dirichlet = True
        elif mode == "hard_mean":
            if not m:
                raise ValueError("mode 'hard_mean' needs Dirichlet vertices")
            is_d = torch.zeros(self.n, dtype=torch.bool)
            is_d[self.dirichlet] = True
            self.free = torch.nonzero(~is_d).reshape(-1)
            self.root_slot = None
            self.encoded_vertices = self.free
            self.hard_dirichlet = True
        else:
            self.free = torch.arange(self.n)
            self.root_slot = None
            self.encoded_vertices = self.free
            self.hard_dirichlet = False
        self.dim = 3 * int(self.encoded_vertices.numel())

    def _origin(self, xD: torch.Tensor) -> torch.Tensor:
        """(..., m, 3) -> (..., n_enc, 3) origin of each encoded vertex."""
        if self.mode == "roots":
            return xD[..., self.root_slot.to(xD.device), :]
        if xD.shape[-2] == 0:
            return torch.zeros(xD.shape[:-2] + (1, 3), dtype=xD.dtype, device=xD.device)
        return xD.mean(-2, keepdim=True)

    def encode(self, x: torch.Tensor, xD: torch.Tensor) -> torch.Tensor:
        """Positions x (..., n, 3), prescribed xD (..., m, 3) -> u (..., d)."""
        xe = x[..., self.encoded_vertices.to(x.device), :]
        u = xe - self._origin(xD)
        return u.reshape(u.shape[:-2] + (self.dim,))

    def decode(self, u: torch.Tensor, xD: torch.Tensor) -> torch.Tensor:
        """u (..., d), prescribed xD (..., m, 3) -> positions (..., n, 3).

        Broadcasts over leading axes; the dtype is that of ``u`` (promoted
        with ``xD``).
        """
        lead = torch.broadcast_shapes(u.shape[:-1], xD.shape[:-2])
        dtype = torch.promote_types(u.dtype, xD.dtype)
        xe = u.reshape(u.shape[:-1] + (-1, 3)).to(dtype) + self._origin(xD.to(dtype))
        if not self.hard_dirichlet:
            return xe.expand(lead + xe.shape[-2:])
        x = torch.empty(lead + (self.n, 3), dtype=dtype, device=u.device)
        x[..., self.free.to(u.device), :] = xe
        x[..., self.dirichlet.to(u.device), :] = xD.to(dtype)
        return x


def coordinates_for(f, mode: str | None = None) -> RelativeCoordinates:
    """The relative coordinates of a scene's trajectories ``f`` (an open ``trajectories.h5``).

    ``mode`` None (the config's autoencoder ``coordinates`` unset): root-relative for rods,
    Dirichlet-mean-relative otherwise; or any mode of :class:`RelativeCoordinates`.
    """
    n = f["rest_positions"].shape[0]
    if mode is None:
        mode = "roots" if str(f.attrs["model"]) == "rods" else "mean"
    if mode == "roots":
        if "root_of" not in f:
            raise ValueError(f"{f.filename}: 'roots' coordinates need the rods' root_of array")
        return RelativeCoordinates(n, f["dirichlet"][()], mode="roots", root_of=f["root_of"][()])
    return RelativeCoordinates(n, f["dirichlet"][()], mode=mode)

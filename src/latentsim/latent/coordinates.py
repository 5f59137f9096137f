"""Relative coordinates: full positions <-> the vector the autoencoder sees (Li et al. 2025, sec. 3.2).

Positions are written relative to the Dirichlet boundary conditions: root-relative for rods,
relative to the mean prescribed position for cloth and solids (or, ``hard_mean``, the free
vertices only, for bodies that are mostly prescribed); optionally (``rigid_frame``) turned with the
prescribed vertices, so that a rigid motion of the boundary moves nothing in the encoded vector.
:func:`coordinates_for` picks a scene's coordinates from its trajectories file.
"""

from __future__ import annotations

import torch

from latentsim.runtime.frame import frame_pose, orthonormal_frame


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

    Rigid frame (``rigid_rest``, not in the paper): positions are first carried into the frame that
    turns with the prescribed vertices, ``x -> R^T (x - c)`` with c the mean prescribed position and
    R = F(x*_D) F(x*_D,rest)^T, F the orthonormal frame of three prescribed vertices (:meth:`pose`,
    :mod:`latentsim.runtime.frame`);
    any of the modes above then applies to the carried positions, and decoding carries back.  A rigid
    motion of the prescribed vertices (a head that turns) then changes nothing the autoencoder sees:
    the latent holds the deformation alone, and the integrator is told the turn
    (:func:`~latentsim.latent.integrator.boundary_inputs`).

    Parameters
    ----------
    n_vertices : number of vertices n.
    dirichlet : (m,) indices of the Dirichlet vertices (order of ``xD``).
    mode : ``"roots"`` or ``"mean"``.
    root_of : (n,) index of each vertex's root vertex (``"roots"`` mode only);
        every root must be a Dirichlet vertex.
    rigid_rest : (m, 3) the prescribed vertices' rest positions, for the rigid frame (None: none); at
        least three of them not on one line.

    Attributes
    ----------
    dim : length d of the encoded vector.
    encoded_vertices : (n_enc,) vertex indices present in the encoded vector.
    rigid : whether positions are encoded in the rigid frame; then ``frame_vertices`` (three
        positions in the Dirichlet list) and ``rest_frame`` F(x*_D,rest) (3, 3).
    """

    def __init__(self, n_vertices: int, dirichlet, mode: str = "mean", root_of=None, rigid_rest=None):
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
        self.rigid = rigid_rest is not None
        self.frame_vertices, self.rest_frame = None, None
        if self.rigid:
            rest = torch.as_tensor(rigid_rest, dtype=torch.float64).reshape(-1, 3)
            if rest.shape[0] != m:
                raise ValueError(f"rigid frame: {rest.shape[0]} rest positions for {m} prescribed vertices")
            self.frame_vertices = frame_vertices(rest)
            self.rest_frame = orthonormal_frame(rest[list(self.frame_vertices)])

    def pose(self, xD: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The rigid frame at prescribed positions xD (..., m, 3): R (..., 3, 3) and c (..., 1, 3), the
        frame taking a vector u of the encoded space to R u + c in the world (rigid coordinates only)."""
        return frame_pose(xD, self.frame_vertices, self.rest_frame.to(xD))

    def _origin(self, xD: torch.Tensor) -> torch.Tensor:
        """(..., m, 3) -> (..., n_enc, 3) origin of each encoded vertex."""
        if self.mode == "roots":
            return xD[..., self.root_slot.to(xD.device), :]
        if xD.shape[-2] == 0:
            return torch.zeros(xD.shape[:-2] + (1, 3), dtype=xD.dtype, device=xD.device)
        return xD.mean(-2, keepdim=True)

    def encode(self, x: torch.Tensor, xD: torch.Tensor) -> torch.Tensor:
        """Positions x (..., n, 3), prescribed xD (..., m, 3) -> u (..., d)."""
        if self.rigid:  # carried into the frame: R^T (y - c), row-wise
            R, c = self.pose(xD)
            x, xD = (x - c) @ R, (xD - c) @ R
        xe = x[..., self.encoded_vertices.to(x.device), :]
        u = xe - self._origin(xD)
        return u.reshape(u.shape[:-2] + (self.dim,))

    def decode(self, u: torch.Tensor, xD: torch.Tensor) -> torch.Tensor:
        """u (..., d), prescribed xD (..., m, 3) -> positions (..., n, 3).

        Broadcasts over leading axes; the dtype is that of ``u`` (promoted
        with ``xD``).
        """
        if self.rigid:  # decoded in the frame, carried back: R y + c
            xD = xD.to(torch.promote_types(u.dtype, xD.dtype))
            R, c = self.pose(xD)
            return self._decode(u, (xD - c) @ R) @ R.transpose(-1, -2) + c
        return self._decode(u, xD)

    def _decode(self, u: torch.Tensor, xD: torch.Tensor) -> torch.Tensor:
        lead = torch.broadcast_shapes(u.shape[:-1], xD.shape[:-2])
        dtype = torch.promote_types(u.dtype, xD.dtype)
        xe = u.reshape(u.shape[:-1] + (-1, 3)).to(dtype) + self._origin(xD.to(dtype))
        if not self.hard_dirichlet:
            return xe.expand(lead + xe.shape[-2:])
        x = torch.empty(lead + (self.n, 3), dtype=dtype, device=u.device)
        x[..., self.free.to(u.device), :] = xe
        x[..., self.dirichlet.to(u.device), :] = xD.to(dtype)
        return x


def frame_vertices(rest: torch.Tensor) -> tuple[int, int, int]:
    """Three of the points ``rest`` (m, 3) that span a frame: the first, the farthest from it, and the
    farthest from the line through those two.  Raises ValueError where no three span one (fewer than
    three points, or all on one line)."""
    rest = torch.as_tensor(rest, dtype=torch.float64)
    if rest.shape[0] >= 3:
        rel = rest - rest[0]
        b = int(torch.linalg.vector_norm(rel, dim=-1).argmax())
        e = rel[b] / torch.linalg.vector_norm(rel[b]).clamp_min(1e-300)
        off = torch.linalg.vector_norm(rel - (rel @ e)[:, None] * e, dim=-1)
        c = int(off.argmax())
        if off[c] > 1e-6 * float(torch.linalg.vector_norm(rel[b])):
            return 0, b, c
    raise ValueError(f"rigid frame: needs at least three prescribed vertices not on one line ({rest.shape[0]} prescribed)")


def coordinates_for(f, mode: str | None = None, rigid_frame: bool = False) -> RelativeCoordinates:
    """The relative coordinates of a scene's trajectories ``f`` (an open ``trajectories.h5``).

    ``mode`` None (the config's autoencoder ``coordinates`` unset): root-relative for rods,
    Dirichlet-mean-relative otherwise; or any mode of :class:`RelativeCoordinates`.  ``rigid_frame``:
    in the frame that turns with the prescribed vertices (their rest positions from ``f``).
    """
    n = f["rest_positions"].shape[0]
    if mode is None:
        mode = "roots" if str(f.attrs["model"]) == "rods" else "mean"
    D = f["dirichlet"][()]
    rest = f["rest_positions"][()][D] if rigid_frame else None
    try:
        if mode == "roots":
            if "root_of" not in f:
                raise ValueError("'roots' coordinates need the rods' root_of array")
            return RelativeCoordinates(n, D, mode="roots", root_of=f["root_of"][()], rigid_rest=rest)
        return RelativeCoordinates(n, D, mode=mode, rigid_rest=rest)
    except ValueError as e:
        raise ValueError(f"{f.filename}: {e}") from None


def coordinates_record(coords: RelativeCoordinates) -> dict:
    """What an autoencoder's file records of its coordinates (:func:`coordinates_for` rebuilds them):
    ``coordinates``, the mode, and ``rigid_frame`` only when set (other files are as before)."""
    return {"coordinates": coords.mode, **({"rigid_frame": True} if coords.rigid else {})}

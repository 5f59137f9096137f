r"""Self-contact: IPC's barrier between a surface and itself (Li et al. 2020), for shells and rods.

    E(x) = sum over pairs  b(d_p(x) - thickness),   b as :func:`~latentsim.physics.barrier.barrier`,

the pairs every vertex and every triangle it is no corner of, and every two edges that share no vertex (a
rod: every two such edges), d_p their distance.  Unlike the colliders' terms, whose stencils are the
surface's own primitives, a pair's four vertices change with x: the term has no fixed stencils
(``stencils`` is empty) and is ``dynamic``: a solver asks it for its gradient and its Hessian as a sparse
matrix over the free degrees of freedom (:meth:`SelfContact.energy_gradient_hessian`), whose pattern
changes from one evaluation to the next (:class:`~latentsim.solve.sparse.LinearSolver` then redoes its
symbolic analysis).

The pairs come from a compiled uniform grid, the primitives' boxes and their distances
(:func:`~latentsim.physics.kernels.distances.self_pairs`: a learned loss asks for the pairs of hundreds of states at
once; the IPC Toolkit's own broad phase hands its candidates over one Python object at a time, 6 ms a state for the
cloth), kept with their state and taken again for the states near it (:class:`~latentsim.physics.kept_pairs.KeptPairs`); the IPC Toolkit gives each near pair's squared distance's
closed-form gradient and Hessian, and the line search's first impact (its additive continuous collision detection).
The barrier is the project's, of the distance itself, as every contact term's.  The energy in PyTorch (the loss, the
autograd oracle), :meth:`SelfContact.energy`, sums the same candidates' distances
(:func:`~latentsim.physics.primitives.point_triangle_distance`,
:func:`~latentsim.physics.primitives.segment_segment_distance`), every state's in one evaluation, over the pairs that
compiled distances without gradients select as within reach (:mod:`~latentsim.physics.kernels.distances`; measuring
every candidate in PyTorch to select them was a quarter of cloth_fold's training).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse
import torch

from latentsim.physics.barrier import barrier, barrier_derivatives
from latentsim.physics.kept_pairs import KeptPairs
from latentsim.physics.kernels.distances import self_pairs, within
from latentsim.physics.mesh_contact import unique_edges
from latentsim.physics.primitives import point_triangle_distance, segment_segment_distance

__all__ = ["SelfContact"]


def _fortran(a, dtype) -> np.ndarray:
    return np.asfortranarray(np.asarray(a, dtype=dtype))


def _candidates(x: np.ndarray, faces: np.ndarray, edges: np.ndarray, r: float):
    """:meth:`SelfContact.candidates` of x (n, 3) over ``faces`` and ``edges`` within r (the reach and the thickness):
    a uniform grid, then the boxes and the distances, compiled (:func:`~latentsim.physics.kernels.distances.self_pairs`;
    k-d trees over the primitives' bounding spheres with array tests took three times as long for the fold's cloth)."""
    return self_pairs(x, faces, edges, r)


class SelfContact:
    """The barrier between a surface's own primitives (module docstring).

    Parameters
    ----------
    n_vertices : the scene's vertex count (the surface's vertices are the scene's own indices).
    primitives : the surface's triangles (T, 3) (a shell) or edges (E, 2) (a rod).
    d_hat, kappa, extend_below : as :func:`~latentsim.physics.barrier.barrier`'s.
    thickness : the distance below which two parts of the surface touch (the shell's thickness, a strand's
        diameter): the barrier is of the distance less it.
    """

    name = "self_contact"
    dynamic = True

    def __init__(self, n_vertices: int, primitives, d_hat: float, kappa: float, thickness: float = 0.0, extend_below: float | None = None):
        import ipctk

        prim = np.asarray(primitives, dtype=np.int64)
        if prim.ndim != 2 or prim.shape[1] not in (2, 3) or (len(prim) and (prim.min() < 0 or prim.max() >= n_vertices)):
            raise ValueError(f"self-contact: primitives of shape {prim.shape} over {n_vertices} vertices (give triangles or edges)")
        self.n = int(n_vertices)
        self.faces = prim if prim.shape[1] == 3 else np.zeros((0, 3), np.int64)
        self.edges = unique_edges(prim) if prim.shape[1] == 3 else np.unique(np.sort(prim, 1), axis=0)
        self.d_hat, self.kappa, self.thickness, self.extend_below = float(d_hat), float(kappa), float(thickness), extend_below
        self.stencils = torch.zeros((0, 4), dtype=torch.int64)
        self._E, self._F = _fortran(self.edges, np.int32), _fortran(self.faces, np.int32)
        self._kept = {}  # reach -> its KeptPairs (:meth:`_found`)
        self._mesh = ipctk.CollisionMesh(_fortran(np.zeros((self.n, 3)), np.float64), self._E, self._F)

    def at(self, frame) -> "SelfContact":
        return self

    # -- pairs ------------------------------------------------------------------------------------
    def candidates(self, x: np.ndarray, reach: float) -> tuple[np.ndarray, int]:
        """The pairs of x (n, 3) that may lie nearer than ``reach`` beyond the thickness, no pair sharing a vertex: their
        vertices (P, 4), the vertex-triangle pairs first (vertex, three corners), then the edge pairs (two ends, two
        ends), and how many are vertex-triangle pairs (:meth:`_found`)."""
        return self._found(np.asarray(x, dtype=np.float64)[None], reach)[0]

    def _found(self, flat: np.ndarray, reach: float) -> list[tuple[np.ndarray, int]]:
        """:meth:`candidates` of each state of flat (S, n, 3) (:func:`_candidates`), found at the reach and the thickness r
        plus twice a margin r / 4, kept with their state and taken again for the states near it
        (:class:`~latentsim.physics.kept_pairs.KeptPairs`)."""
        r = float(reach) + self.thickness
        if float(reach) not in self._kept:
            self._kept[float(reach)] = KeptPairs((self.n, 3), r / 4)
        kept = self._kept[float(reach)]
        return kept(flat, lambda states: [_candidates(x, self.faces, self.edges, r + 2 * kept.margin) for x in states])

    @staticmethod
    def _distances(x: torch.Tensor, ids: np.ndarray, n_fv: int, state=None) -> torch.Tensor:
        """The unsigned distance of each pair ids (P, 4) in x (n, 3), or with ``state`` (P,) in x[state] of x (S, n, 3)."""
        it = torch.as_tensor(ids)
        y = x[..., it, :] if state is None else x[torch.as_tensor(state)[:, None], it]  # (P, 4, 3)
        return torch.cat([point_triangle_distance(y[:n_fv, 0], y[:n_fv, 1:]), segment_segment_distance(y[n_fv:, :2], y[n_fv:, 2:])])

    def _batch(self, flat: np.ndarray, reach: float):
        """Every state's candidates of flat (S, n, 3), the vertex-triangle pairs of all states first: (state (P,),
        ids (P, 4), how many are vertex-triangle pairs)."""
        per = self._found(np.asarray(flat, dtype=np.float64), reach)
        fv = [(np.full(k, s), ids[:k]) for s, (ids, k) in enumerate(per)]
        ee = [(np.full(len(ids) - k, s), ids[k:]) for s, (ids, k) in enumerate(per)]
        state = np.concatenate([s for s, _ in fv + ee]) if per else np.zeros(0, np.int64)
        ids = np.concatenate([i for _, i in fv + ee]) if per else np.zeros((0, 4), np.int64)
        return state.astype(np.int64), ids.reshape(-1, 4), sum(len(i) for _, i in fv)

    def _near(self, flat: np.ndarray, state: np.ndarray, ids: np.ndarray, n_fv: int, reach: float):
        """The pairs (state, ids, n_fv as :meth:`_batch`'s) of flat (S, n, 3) that may lie nearer than ``reach`` beyond
        the thickness (:func:`~latentsim.physics.kernels.distances.within`: all those that do in PyTorch's measure, and
        those within its slack of the reach, whose barrier is zero)."""
        near = within(flat, state, ids, n_fv, reach + self.thickness)
        return state[near], ids[near], int(near[:n_fv].sum())

    def pairs(self, x: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray, int]:
        """The pairs of x (n, 3) nearer than ``reach`` beyond the thickness: their vertices (P, 4), their signed distances
        (P,) and how many are vertex-triangle pairs (the first ones)."""
        x = np.asarray(x, dtype=np.float64)
        ids, n_fv = self.candidates(x, reach)
        _, ids, n_fv = self._near(x[None], np.zeros(len(ids), np.int64), ids, n_fv, reach)
        d = self._distances(torch.as_tensor(x), ids, n_fv).numpy() - self.thickness
        keep = d < reach
        return ids[keep], d[keep], int(keep[:n_fv].sum())

    # -- energy ---------------------------------------------------------------------------------------
    def energy(self, x: torch.Tensor, frame=None) -> torch.Tensor:
        """The barrier summed over the pairs within reach, x (..., n, 3) -> (...), differentiable (the pairs are those
        of each state, found without gradients, all states' measured together)."""
        flat = x.reshape(-1, self.n, 3)
        y = flat.detach().cpu().numpy()
        state, ids, n_fv = self._near(y, *self._batch(y, self.d_hat), self.d_hat)  # measured without gradients first
        out = torch.zeros(len(flat), dtype=x.dtype, device=x.device)
        if len(ids):  # the pairs within reach again, with gradients
            b = barrier(self._distances(flat, ids, n_fv, state) - self.thickness, self.d_hat, self.kappa, self.extend_below)
            out = out.index_add(0, torch.as_tensor(state, device=x.device), b)
        return out.reshape(x.shape[:-2])

    def distances(self, x: torch.Tensor, reach: float) -> torch.Tensor:
        """The least signed distance between two parts of the surface in each state, x (..., n, 3) -> (...); ``reach``
        where no pair is nearer than it."""
        flat = x.detach().reshape(-1, self.n, 3).cpu()
        state, ids, n_fv = self._near(flat.numpy(), *self._batch(flat.numpy(), reach), reach)
        out = torch.full((len(flat),), float(reach), dtype=x.dtype)
        if len(ids):
            d = self._distances(flat, ids, n_fv, state) - self.thickness
            out = out.scatter_reduce(0, torch.as_tensor(state), d.to(x.dtype), reduce="amin")
        return out.clamp(max=float(reach)).reshape(x.shape[:-2])

    def energy_gradient_hessian(self, x: np.ndarray, free_dofs: np.ndarray | None = None, project: bool = True, hessian: bool = True):
        """E, its gradient (3n,) and (with ``hessian``) its Hessian over ``free_dofs`` (all when None) as the upper
        triangle in CSR, per pair b'(d) grad d and b''(d) grad d grad d^T + b'(d) Hess d (the distance's derivatives
        from the IPC Toolkit's squared distance s: grad d = grad s / 2d, Hess d = Hess s / 2d - grad s grad s^T / 4d^3),
        PSD-projected per pair when ``project``."""
        import ipctk

        x = np.asarray(x, dtype=np.float64)
        ids, d, n_fv = self.pairs(x, self.d_hat)
        grad = np.zeros(3 * self.n)
        free = np.arange(3 * self.n) if free_dofs is None else np.asarray(free_dofs, dtype=np.int64)
        if not len(ids):
            return 0.0, grad, scipy.sparse.csr_matrix((len(free), len(free))) if hessian else None
        dt = torch.as_tensor(d)
        e = float(barrier(dt, self.d_hat, self.kappa, self.extend_below).sum())
        db, d2b = (t.numpy() for t in barrier_derivatives(dt, self.d_hat, self.kappa, self.extend_below))
        y = x[ids]  # (P, 4, 3)
        kinds = [(ipctk.point_triangle_distance_gradient, ipctk.point_triangle_distance_hessian)] * n_fv
        kinds += [(ipctk.edge_edge_distance_gradient, ipctk.edge_edge_distance_hessian)] * (len(ids) - n_fv)
        gs = np.array([g(*p) for (g, _), p in zip(kinds, y)]).reshape(len(ids), 12)
        rho = d + self.thickness
        gd = gs / (2 * rho[:, None])
        dofs = (3 * ids[:, :, None] + np.arange(3)).reshape(len(ids), 12)
        np.add.at(grad, dofs, db[:, None] * gd)
        if not hessian:
            return e, grad, None
        Hs = np.array([h(*p) for (_, h), p in zip(kinds, y)]).reshape(len(ids), 12, 12)
        Hd = Hs / (2 * rho[:, None, None]) - gs[:, :, None] * gs[:, None, :] / (4 * rho[:, None, None] ** 3)
        H = d2b[:, None, None] * gd[:, :, None] * gd[:, None, :] + db[:, None, None] * Hd
        if project:
            w, Q = np.linalg.eigh(H)
            H = (Q * np.maximum(w, 0.0)[:, None, :]) @ Q.transpose(0, 2, 1)
        local = -np.ones(3 * self.n, dtype=np.int64)
        local[free] = np.arange(len(free))
        r = np.broadcast_to(local[dofs][:, :, None], H.shape).reshape(-1)
        c = np.broadcast_to(local[dofs][:, None, :], H.shape).reshape(-1)
        keep = (r >= 0) & (c >= r)
        U = scipy.sparse.coo_matrix((H.reshape(-1)[keep], (r[keep], c[keep])), shape=(len(free), len(free))).tocsr()
        U.sum_duplicates()
        return e, grad, U

    def first_impact(self, x: np.ndarray, dx: np.ndarray, frame=None) -> float:
        """The largest fraction t of the step x -> x + dx (n, 3) over which no two parts of the surface come within the
        thickness (the toolkit's collision-free step size, additive CCD); inf where the whole step is free."""
        import ipctk

        x = np.asarray(x, dtype=np.float64)
        t = ipctk.compute_collision_free_stepsize(self._mesh, _fortran(x, np.float64), _fortran(x + dx, np.float64), self.thickness, None, ipctk.AdditiveCCD())
        return math.inf if t >= 1.0 else float(t)

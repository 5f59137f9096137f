r"""The compiled kernels of one energy term, and their batching over stencils, threads and states.

Every ``EnergyTerm`` with compiled kernels names them (``EnergyTerm.kernel_spec``:
a :class:`KernelSpec` of an energy kernel, an energy + gradient kernel, a run
kernel, the rest data and the stencil size, the kernels in ``kernels.tets``,
``kernels.rods``, ``kernels.shells``).  :class:`TermKernel` holds them with
float64 copies of the term's stencils and offers

- ``energy(x)``: the term's energy at x (n, 3), gathered inside the kernel;
- ``energy_gradient(x, grad)``: the energy, and the gradient added into the
  (3n,) ``grad``, in one pass (the line search: the accepted trial state's
  gradient then serves the next convergence test, and the Hessian is built
  only when that test fails);
- ``energies(x, grad)``: the same for L states at once, x (n, 3, L) with the
  state index innermost (``core.as_lanes``: the kernels vectorise over the
  states, and each state's bits are those of a one-state pass);
- ``accumulate(x, grad, data, slots, project)``: per stencil, the gradient and
  the Hessian (exact, or eigenvalue-clamped), added straight into the (3n,)
  gradient and into the data array of the free-DoF Hessian (the CSR data, or
  the banded storage) at precomputed slot indices
  (``solve.sparse.HessianPattern.stencil_slots``): no per-stencil blocks are
  materialised, no COO->CSR or CSR->band conversion runs;
- ``local(x, project)``: per-stencil g (E, 3k) and H (E, 3k, 3k), the layout
  of ``EnergyTerm.local_gradient_hessian``.

Threads, and determinism.  Each kernel loops over an ``order`` of stencil
indices: the solver gives every term two halves whose stencils share no
vertex (a median cut of a reverse Cuthill-McKee vertex order) and the
separator between them (``split_stencils``, a static partition); on two
threads the halves run at once, since no gradient entry or Hessian slot is
written by both, then the separator, and the energies are summed in the fixed
order (first half + second half) + separator.  Many states at once (the
self-supervised losses) split the states over threads instead
(``batch_energy_gradient``: contiguous, fixed ranges of states, each state
computed whole by one thread, in blocks of ``LANES`` states per kernel call).
No kernel uses numba's parallel loops, so the numba threading layer plays no
part: the bits do not depend on the thread count or on the machine's load.
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np
import scipy.sparse
import torch
from scipy.sparse.csgraph import reverse_cuthill_mckee

from latentsim.physics.kernels.core import SCATTER, STORE


def available() -> bool:
    """True: numba is a pinned dependency, so every term with a ``kernel_spec`` has its kernels."""
    return True


@dataclasses.dataclass(frozen=True)
class KernelSpec:
    """The compiled kernels of one energy term, as ``EnergyTerm.kernel_spec`` names them.

    Attributes
    ----------
    energy : ``energy(x, st, order, *args) -> (L,)``, the summed energy of the stencils ``order``
        in each lane of x: one state x (n, 3), L = 1, or L states x (n, 3, L), the state index
        innermost (``core.as_lanes``).
    energy_gradient : ``energy_gradient(x, st, order, *args, grad) -> (L,)``, the same energies
        and the gradients added into ``grad`` (x's shape).
    run : ``run(x, st, order, *args, project, [basis,] grad, data, slots, g_out, H_out, mode)``,
        one state x (n, 3): the energy, and the gradient and Hessian scattered (SCATTER) or
        stored per stencil (STORE).
    args : the per-stencil rest data, float64 arrays with the stencil axis first.
    k : vertices per stencil.
    basis : (3k, 3k-3) translation-free basis of the projection (``core.translation_free_basis``),
        or None for a run kernel that projects without one.
    """

    energy: Callable
    energy_gradient: Callable
    run: Callable
    args: tuple
    k: int
    basis: np.ndarray | None = None


def float64_array(t, count: int | None = None) -> np.ndarray:
    """A contiguous float64 NumPy copy of tensor ``t``, broadcast to (count,) when given."""
    a = t.detach().cpu().numpy().astype(np.float64)
    if count is not None:
        a = np.broadcast_to(a, (count,))
    return np.ascontiguousarray(a)


_EMPTY_F = np.zeros(0)
_EMPTY_G = np.zeros((0, 0))
_EMPTY_H = np.zeros((0, 0, 0))
_EMPTY_S = np.zeros((0, 0), dtype=np.int32)


class TermKernel:
    """Compiled energy, gradient and Hessian of one ``EnergyTerm`` (see the module docstring).

    Built by ``term_kernel(term)`` from the term's name, stencils (E, k) and
    ``KernelSpec``; holds an int64 NumPy copy of the stencils.  The stencils
    are visited group by group (``groups``: all of them, or the two halves and the separator that
    :func:`split_stencils` makes); with ``threads = 2`` the two halves run
    concurrently (the kernels release the GIL; halves share no vertex, so no
    gradient entry or Hessian slot is written by both), then the separator.
    Every path visits the groups in the same order, so the result does not
    depend on ``threads``.
    """

    # fewer stencils than this: a thread hand-off costs more than it saves (hair rotation, 3,400 rod
    # stencils per term, ran slower on two threads; the armadillo, 12k tets, faster)
    MIN_PARALLEL = 5000

    def __init__(self, name: str, stencils, spec: KernelSpec):
        self.name = name
        self.stencils = np.ascontiguousarray(stencils, dtype=np.int64)
        self.k = spec.k
        self._energy = spec.energy
        self._energy_gradient = spec.energy_gradient
        self._run = spec.run
        self._args = spec.args
        self._basis = spec.basis  # translation-free basis (projection), None for tets / stretch
        self._all = np.arange(len(self.stencils), dtype=np.int64)
        self.groups = (self._all,)
        self.threads = 1
        self._serial, self._serial_of = None, None  # the groups concatenated, for one serial call

    def _visit(self, fn, total: bool = True) -> float:
        """sum of fn(order) over the groups, the two halves concurrently when threaded.

        Serially it is one call over the groups concatenated (the same visiting order, so the
        same scatter), except for a kernel large enough to run threaded whose energy is wanted
        (``total=True``): that energy is summed group by group, as the threaded path sums it,
        so its last bits do not depend on the thread count.
        """
        g = self.groups
        large = len(self._all) >= self.MIN_PARALLEL
        if len(g) == 3 and self.threads > 1 and large:
            other = _pool().submit(fn, g[0])
            second = fn(g[1])
            return other.result() + second + fn(g[2])
        if (total and large) or len(g) == 1:
            return sum(fn(order) for order in g)
        if self._serial_of is not g:
            self._serial, self._serial_of = np.concatenate(g), g
        return fn(self._serial)

    def _call(self, x, project, grad, data, slots, g_out, H_out, mode) -> float:
        x = np.ascontiguousarray(x, dtype=np.float64)
        extra = () if self._basis is None else (self._basis,)
        run, st, args = self._run, self.stencils, self._args
        return self._visit(lambda order: run(x, st, order, *args, project, *extra, grad, data, slots, g_out, H_out, mode),
                           total=mode != STORE)  # fmt: skip

    def energies(self, x: np.ndarray, grad: np.ndarray | None = None) -> np.ndarray:
        """The term's energy in each lane of x: one state (n, 3) -> (1,), or L states (n, 3, L),
        the state index innermost (C-contiguous float64) -> (L,); with ``grad`` (x's shape),
        the gradients added into it, in the same pass."""
        st, args = self.stencils, self._args
        if grad is None:
            fn = self._energy
            return self._visit(lambda order: fn(x, st, order, *args))
        fn = self._energy_gradient
        return self._visit(lambda order: fn(x, st, order, *args, grad))

    def energy(self, x: np.ndarray) -> float:
        """The term's energy at x (n, 3)."""
        return float(self.energies(np.ascontiguousarray(x, dtype=np.float64))[0])

    def accumulate(self, x, grad, data, slots, project: bool) -> float:
        """grad (3n,) += gradient; data[slots] += upper triangles of the stencil Hessians;
        returns the energy (the same sum, to the bit, as ``energy_gradient``'s).

        slots : (E, 3k (3k+1) / 2) int32 target indices of the upper-triangle
        entries of each stencil Hessian (row-major), -1 for dropped entries.
        """
        return self._call(x, bool(project), grad, data, slots, _EMPTY_G, _EMPTY_H, SCATTER)

    def energy_gradient(self, x, grad) -> float:
        """grad (3n,) += gradient; returns the energy (one pass, no Hessian)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        return float(self.energies(x, grad.reshape(x.shape, copy=False))[0])  # a view: the kernel adds into it

    def local(self, x, project: bool):
        """Per-stencil g (E, 3k) and H (E, 3k, 3k), like ``EnergyTerm.local_gradient_hessian``."""
        E, n3 = self.stencils.shape[0], 3 * self.k
        g, H = np.zeros((E, n3)), np.zeros((E, n3, n3))
        self._call(x, bool(project), _EMPTY_F, _EMPTY_F, _EMPTY_S, g, H, STORE)
        return g, H


_POOL = None


def _pool():
    """One worker thread, shared by every kernel (the caller's thread runs the other half)."""
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(1, thread_name_prefix="latentsim-kernels")
    return _POOL


def split_stencils(kernels, n_vertices: int, threads: int = 2) -> None:
    """Give each kernel two vertex-disjoint halves of its stencils and the separator.

    The vertices are ordered by reverse Cuthill-McKee on the graph of all the
    kernels' stencils (neighbours end up close in the order) and cut at the
    median: stencils wholly below the cut form the first half, wholly above
    the second, the rest (a layer about one stencil thick) the separator.
    ``threads`` (1 or 2) sets whether the halves run concurrently; the result
    is the same either way.
    """
    rows, cols = [], []
    for k in kernels:
        st = k.stencils
        for a in range(st.shape[1]):
            for b in range(st.shape[1]):
                if a != b:
                    rows.append(st[:, a])
                    cols.append(st[:, b])
    rank = np.arange(n_vertices)
    if rows:
        r, c = np.concatenate(rows), np.concatenate(cols)
        graph = scipy.sparse.csr_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(n_vertices, n_vertices))
        rank[reverse_cuthill_mckee(graph, symmetric_mode=True)] = np.arange(n_vertices)
    low = rank < n_vertices // 2
    for k in kernels:
        inside = low[k.stencils]
        first, second = inside.all(1), ~inside.any(1)
        k.groups = tuple(np.flatnonzero(m).astype(np.int64) for m in (first, second, ~(first | second)))
        k.threads = int(threads)


def term_kernel(term) -> TermKernel | None:
    """The compiled kernels of ``term`` (its ``kernel_spec``), or None for a term without."""
    spec = term.kernel_spec()
    return None if spec is None else TermKernel(term.name, term.stencils.cpu().numpy(), spec)


# ---------------------------------------------------------------------------
# many states at once: the self-supervised losses
# ---------------------------------------------------------------------------
# states per kernel call: the block's per-stencil scratch (a few (3, 3, LANES) arrays) stays in the
# L1/L2 cache.  On batches of 256 states (benchmarks/bench_energy_batch.py) blocks of 32 to 64 ran
# fastest; blocks of 8 ran 1.7-3x slower, one block of 256 up to 1.4x slower.
LANES = 64


def batch_energy_gradient(kernels, x, gradient: bool = True, threads: int = 1):
    """Energies and gradients of the summed terms at each of B states, by the compiled kernels.

    The states go to the kernels in blocks of ``LANES``, transposed to (n, 3, L), the state index
    innermost (``TermKernel.energies``); each state's energy and gradient are, to the bit, those
    of a one-state pass.

    Parameters
    ----------
    kernels : the ``TermKernel`` of every term.
    x : (B, n, 3) float64 states.
    gradient : also return the gradients (else only the energies, a cheaper pass).
    threads : states are split over this many threads (the kernels release the GIL); each state
        is computed whole by one thread, so the result does not depend on ``threads``.

    Returns
    -------
    E : (B,), G : (B, n, 3) or None
    """
    x = np.asarray(x, dtype=np.float64)
    B = x.shape[0]
    E = np.zeros(B)
    G = np.zeros(x.shape) if gradient else None

    def work(lo, hi):
        for a in range(lo, hi, LANES):
            b = min(a + LANES, hi)
            xl = np.ascontiguousarray(x[a:b].transpose(1, 2, 0))
            gl = np.zeros(xl.shape) if gradient else None
            E[a:b] = sum(k.energies(xl, gl) for k in kernels)
            if gradient:
                G[a:b] = gl.transpose(2, 0, 1)

    threads = max(1, min(int(threads), B))
    if threads == 1:
        work(0, B)
    else:
        bounds = np.linspace(0, B, threads + 1).round().astype(int)
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(work, bounds[:-1], bounds[1:]))
    return E, G


class _CompiledEnergy(torch.autograd.Function):
    """E(x) summed over the kernels' terms, x (..., n, 3) -> (...); first derivatives only."""

    @staticmethod
    def forward(ctx, x, kernels, threads):
        lead = x.shape[:-2]
        flat = x.detach().reshape(-1, *x.shape[-2:]).numpy()
        E, G = batch_energy_gradient(kernels, flat, gradient=ctx.needs_input_grad[0], threads=threads)
        if G is not None:
            ctx.save_for_backward(torch.from_numpy(G).reshape(x.shape))
        return torch.from_numpy(E).reshape(lead)

    @staticmethod
    def backward(ctx, grad_energy):
        if torch.is_grad_enabled():  # create_graph: a second derivative would silently miss this energy
            raise RuntimeError("compiled energies have first derivatives only; use the terms' PyTorch energies (potential.kernels = None) for Hessians")
        (G,) = ctx.saved_tensors
        return grad_energy[..., None, None] * G, None, None


def compiled_energy(kernels, x: torch.Tensor, threads: int | None = None) -> torch.Tensor:
    """The elastic energy of x (..., n, 3) (CPU, float64) by the compiled kernels, differentiable
    once (its backward is the kernels' gradient; a second derivative raises).  ``threads``:
    default ``torch.get_num_threads()``, the thread budget the caller set for torch."""
    if x.device.type != "cpu" or x.dtype != torch.float64:
        raise ValueError(f"compiled energies take float64 CPU states, got {x.dtype} on {x.device}")
    return _CompiledEnergy.apply(x, kernels, int(threads or torch.get_num_threads()))


def with_compiled_elastic(potential):
    """A copy of ``potential`` (``ElasticPotential`` or ``IncrementalPotential``) whose elastic
    energy runs the compiled kernels of its terms (5-8x faster than the batched PyTorch energy
    under autograd on many states; first derivatives only), or ``potential`` itself when a term
    has no kernel.  The same formulas: ``tests/physics/test_kernels.py`` checks them against the terms."""
    if not dataclasses.is_dataclass(potential):  # a wrapper (tests): leave it as it is
        return potential
    ks = [term_kernel(t) for t in potential.terms]
    if not ks or any(k is None for k in ks):
        return potential
    return dataclasses.replace(potential, kernels=ks)


__all__ = [
    "KernelSpec",
    "TermKernel",
    "available",
    "batch_energy_gradient",
    "compiled_energy",
    "float64_array",
    "split_stencils",
    "term_kernel",
    "with_compiled_elastic",
]

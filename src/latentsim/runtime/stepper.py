"""The one interface of every latent runtime: a :class:`Stepper` steps one frame.

A frame of the latent dynamics (Li et al. 2025, Eq. 3, and the decode)::

    z_t = integrate(z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2})
    x_t = decode(z_t, x*_D,t)

The NumPy (:class:`latentsim.runtime.numpy_stepper.NumpyStepper`), compiled
(:class:`latentsim.runtime.compiled.CompiledStepper`), exported-PyTorch and
eager-PyTorch steppers (:mod:`latentsim.runtime.torch_stepper`) all satisfy it,
so that timing (:func:`latentsim.runtime.timing.time_step`) and the rollout stage
treat them alike: a stepper converts a frame's arrays into the types it takes
itself (:meth:`Stepper.inputs`), with no type switch in the caller.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

__all__ = ["Stepper", "rollout_runtime"]


@runtime_checkable
class Stepper(Protocol):
    """One latent frame: integration, decoding, or both.

    Attributes
    ----------
    r, k, n : latent dimension, boundary-condition parameters per frame, vertices.
    dtype : the network's NumPy dtype (positions are always float64).

    The arrays that :meth:`integrate`, :meth:`decode` and :meth:`step` return may
    be the stepper's own buffers, overwritten by its next call; pass ``out=`` (or
    copy) to keep them.
    """

    r: int
    k: int
    n: int
    dtype: np.dtype

    def inputs(self, z_prev, z_prev2, p, p_prev, p_prev2, xD) -> tuple:
        """One frame's arguments in the types this stepper takes: new arrays (or tensors)
        of z_{t-1}, z_{t-2} (r,) and p_t, p_{t-1}, p_{t-2} (k,) in the network dtype, xD (m, 3) float64."""
        ...

    def integrate(self, z_prev, z_prev2, p, p_prev, p_prev2, out=None) -> Any:
        """z_t (r,) from z_{t-1}, z_{t-2} (r,) and p_t, p_{t-1}, p_{t-2} (k,)."""
        ...

    def decode(self, z, xD, out=None) -> Any:
        """Positions x (n, 3) float64 of latent z (r,) with Dirichlet positions xD (m, 3)."""
        ...

    def step(self, z_prev, z_prev2, p, p_prev, p_prev2, xD, z_out=None, x_out=None) -> tuple:
        """One frame: (z_t (r,), x_t (n, 3))."""
        ...


def rollout_runtime(stepper: Stepper, z0, z1, bc, dirichlet_positions) -> dict:
    """Autoregressive rollout with a stepper that takes NumPy arrays (the NumPy or compiled one; no divergence test).

    z0, z1 : (r,); bc : (T, k); dirichlet_positions : (T, m, 3).
    Returns ``latents`` (T, r) in the network dtype and ``positions`` (T, n, 3) float64.
    """
    bc = np.asarray(bc, dtype=stepper.dtype)
    xD = np.asarray(dirichlet_positions, dtype=np.float64)
    T = bc.shape[0]
    Z = np.full((T, stepper.r), np.nan, dtype=stepper.dtype)
    X = np.full((T, stepper.n, 3), np.nan)
    Z[0], Z[1] = z0, z1
    stepper.decode(Z[0], xD[0], out=X[0])
    stepper.decode(Z[1], xD[1], out=X[1])
    for t in range(2, T):
        stepper.step(Z[t - 1], Z[t - 2], bc[t], bc[t - 1], bc[t - 2], xD[t], z_out=Z[t], x_out=X[t])
        if not np.isfinite(Z[t]).all():
            break
    return {"latents": Z, "positions": X}

"""The latent integrator of Li et al. 2025 (sec. 3.3, Eq. 3): an MLP (SiLU) mapping
``[z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}]`` to ``z_t``.

Its training loss is :mod:`latentsim.latent.loss`, its training loop
:mod:`latentsim.latent.training`.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch import nn

from latentsim.runtime.frame import frame_inputs


class LatentIntegrator(nn.Module):
    """z_t = I(z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}) (paper Eq. 3).

    An MLP with SiLU (Swish) activations.  Inputs are standardised with
    statistics stored as buffers (:meth:`fit_normalization`).  With
    ``residual=True`` (default) the network predicts the increment,
    ``z_t = z_{t-1} + mu_dz + sigma_dz * MLP(q)``, where mu_dz, sigma_dz are
    the mean/std of ``z_t - z_{t-1}`` over the training triplets: latents
    change little per frame, so a zero MLP output already means "keep the
    previous latent (plus the mean drift)".  With ``residual=False`` the
    output is ``z_t = mu_z + sigma_z * MLP(q)`` (statistics of z_t).

    Parameters
    ----------
    latent_dim : r.
    bc_dim : k, length of one boundary-condition vector p_t (may be 0).
    widths : hidden widths.
    residual : see above.
    origin : whether each p_t ends with the mean prescribed position at frame t, the origin of the
        relative coordinates (:func:`boundary_inputs`; ``bc_dim`` counts it).
    """

    def __init__(self, latent_dim: int, bc_dim: int, widths: Sequence[int], residual: bool = True, origin: bool = False):
        super().__init__()
        widths = [int(w) for w in widths]
        self.hparams = {"latent_dim": int(latent_dim), "bc_dim": int(bc_dim), "widths": widths, "residual": bool(residual)}
        if origin:  # recorded only when set: the files of integrators without it are as before
            self.hparams["origin"] = True
        self.origin = bool(origin)
        self.latent_dim, self.bc_dim, self.residual = int(latent_dim), int(bc_dim), bool(residual)
        in_dim = 2 * latent_dim + 3 * bc_dim
        layers: list[nn.Module] = []
        prev = in_dim
        for w in widths:
            layers += [nn.Linear(prev, w), nn.SiLU()]
            prev = w
        layers.append(nn.Linear(prev, latent_dim))
        self.mlp = nn.Sequential(*layers)
        self.register_buffer("in_mean", torch.zeros(in_dim))
        self.register_buffer("in_std", torch.ones(in_dim))
        self.register_buffer("out_mean", torch.zeros(latent_dim))
        self.register_buffer("out_std", torch.ones(latent_dim))

    @staticmethod
    def _std(a: torch.Tensor) -> torch.Tensor:
        s = a.std(0, unbiased=False) if a.shape[0] > 1 else torch.ones_like(a[0])
        return torch.where(s > 1e-12, s, torch.ones_like(s))

    @torch.no_grad()
    def fit_normalization(self, z, z_prev, z_prev2, p, p_prev, p_prev2) -> None:
        """Set the normalisation buffers from training triplets (each (N, .))."""
        q = torch.cat([z_prev, z_prev2, p, p_prev, p_prev2], -1).to(self.in_mean)
        self.in_mean.copy_(q.mean(0))
        self.in_std.copy_(self._std(q))
        tgt = (z - z_prev) if self.residual else z
        tgt = tgt.to(self.out_mean)
        self.out_mean.copy_(tgt.mean(0))
        self.out_std.copy_(self._std(tgt))

    def forward(self, z_prev, z_prev2, p, p_prev, p_prev2) -> torch.Tensor:
        """All inputs (B, .) -> z_t (B, r)."""
        dt = self.in_mean.dtype
        z_prev = z_prev.to(dt)
        q = torch.cat([z_prev, z_prev2.to(dt), p.to(dt), p_prev.to(dt), p_prev2.to(dt)], -1)
        y = self.out_mean + self.out_std * self.mlp((q - self.in_mean) / self.in_std)
        return z_prev + y if self.residual else y


def boundary_inputs(bc, dirichlet_positions, origin: bool, coords=None):
    """The p_t an integrator takes at each frame, in the type of ``bc`` (a NumPy array or a tensor): the
    boundary-condition parameters ``bc`` (T, k); in coordinates with a rigid frame (``coords.rigid``,
    :class:`~latentsim.latent.coordinates.RelativeCoordinates`) each of their 3-vectors (a program's
    velocity and angular velocity) carried into the frame, R^T v, followed by the nine entries of R^T
    (row by row: the world's axes, and so gravity, as the frame sees them); and, with ``origin``, the
    mean of the frame's prescribed positions ``dirichlet_positions`` (T, m, 3) appended last.

    The latent coordinates are relative to that mean (``mean``), and the parameters of a program are its
    velocities: without it an integrator does not know where the cloth or solid is in the world, and so
    where a static collider is relative to it (``integrator.origin_input``; not in the paper).  In a rigid
    frame the latent holds no turn of the boundary, and the frame's orientation and the program's
    velocities in it are what tell the integrator how inertia and gravity act (``autoencoder.rigid_frame``;
    not in the paper)."""
    rigid = coords is not None and coords.rigid
    if not (origin or rigid):
        return bc
    is_tensor = torch.is_tensor(bc)
    p = (bc if is_tensor else torch.as_tensor(np.asarray(bc))).reshape(len(bc), -1)
    xD = torch.as_tensor(dirichlet_positions)
    if rigid:
        R, _ = coords.pose(xD.to(torch.float64))
        p = frame_inputs(p.to(R), R).to(p)
    if origin:
        p = torch.cat([p, xD.mean(-2).to(p)], -1)
    return p if is_tensor else p.numpy()

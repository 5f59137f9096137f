"""Autoregressive inference in the latent space (Li et al. 2025, sec. 3.3): from the first two
frames' latents, each next latent by the integrator from the boundary-condition history alone,
decoded with the prescribed Dirichlet positions; with divergence detection.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import nn

from latentsim.latent.autoencoder import Autoencoder, decode_latents
from latentsim.latent.base import potential_on
from latentsim.latent.coordinates import RelativeCoordinates
from latentsim.latent.integrator import boundary_inputs


@torch.no_grad()
def rollout(
    integrator: Callable,
    ae: Autoencoder,
    coords: RelativeCoordinates,
    z0: torch.Tensor,
    z1: torch.Tensor,
    bc: torch.Tensor,
    dirichlet_positions: torch.Tensor,
    potential=None,
    max_extent: float | None = None,
    rest_positions: torch.Tensor | None = None,
    correct: Callable | None = None,
) -> dict:
    """Autoregressive latent rollout from the first two frames' latents.

    Frame t >= 2 is ``integrator(z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2})``;
    only the boundary-condition history is fed in (p_t: ``bc``, and the frame's mean prescribed
    position for an integrator trained with it, :func:`~latentsim.latent.integrator.boundary_inputs`).
    All latents are then decoded with the prescribed Dirichlet positions of their frame.

    Divergence: the first frame whose latent is NaN/inf, whose decoded
    positions are non-finite, or (when ``max_extent`` is given) whose decoded
    bounding-box diagonal exceeds ``max_extent`` times the reference diagonal
    (of ``rest_positions`` (n, 3) if given, else of decoded frame 0).  Rolling
    out stops there; that frame keeps its computed values and all later
    frames are NaN.

    Parameters
    ----------
    z0, z1 : (r,) latents of frames 0 and 1.
    bc : (T, k) boundary-condition parameters p_t.
    dirichlet_positions : (T, m, 3) prescribed Dirichlet positions.
    potential : optional IncrementalPotential; if given, per-frame
        ``kinetic_energy`` and ``incremental_potential`` are returned too.
    correct : optional ``(t, z_t) -> z_t'`` applied to z0, z1 and each finite predicted latent
        before it is stored and fed to the next step (the contact projection fed back,
        :meth:`latentsim.latent.projection.ContactProjection.step`).

    Returns
    -------
    dict with ``latents`` (T, r) float32, ``positions`` (T, n, 3) float64 (CPU),
    ``diverged_frame`` (int, -1 if stable) and, with ``potential``,
    ``kinetic_energy`` (T,) (NaN at frame 0) and ``incremental_potential``
    (T,) (NaN at frames 0, 1).
    """
    z0, z1 = torch.as_tensor(z0), torch.as_tensor(z1)
    bc, dirichlet_positions = torch.as_tensor(bc), torch.as_tensor(dirichlet_positions)
    T = int(bc.shape[0])
    if dirichlet_positions.shape[0] != T:
        raise ValueError("bc and dirichlet_positions must have the same number of frames")
    bc = boundary_inputs(bc.reshape(T, -1), dirichlet_positions, getattr(integrator, "origin", False), coords)
    mods = [m for m in (integrator, ae) if isinstance(m, nn.Module)]
    was = [m.training for m in mods]
    for m in mods:
        m.eval()
    stop = None
    if correct is not None and max_extent is not None and rest_positions is not None:  # no correcting of frames past divergence
        limit = float(max_extent) * float(_diagonal(torch.as_tensor(rest_positions, dtype=torch.float64)))
        stop = lambda t, z: past_extent(ae, coords, z, dirichlet_positions[t], limit)  # noqa: E731
    try:
        Z, last, diverged = _integrate(integrator, z0, z1, bc.reshape(T, -1).to(ae.pca_in.weight.device, torch.float32), correct, stop)
        X = torch.full((T, coords.n, 3), float("nan"), dtype=torch.float64)
        X[: last + 1] = decode_latents(ae, coords, Z[: last + 1], dirichlet_positions[: last + 1].to(Z.device)).cpu()
    finally:
        for m, w in zip(mods, was):
            m.train(w)
    hit = _first_bad_frame(X[: last + 1], max_extent, rest_positions)
    if hit >= 0:
        diverged = hit if diverged < 0 else min(diverged, hit)
    Z = Z.cpu()
    if diverged >= 0:
        Z[diverged + 1 :] = float("nan")
        X[diverged + 1 :] = float("nan")
    out = {"latents": Z, "positions": X, "diverged_frame": int(diverged)}
    if potential is not None:
        out.update(_energies(potential, coords, X, dirichlet_positions))
    return out


def _integrate(integrator: Callable, z0: torch.Tensor, z1: torch.Tensor, bc: torch.Tensor, correct: Callable | None = None,
               stop: Callable | None = None):  # fmt: skip
    """Latents (T, r) float32 on the device of ``bc`` (T, k): z0, z1, then the integrator's (each
    through ``correct`` where given), until the first non-finite one or the first for which ``stop(t, z_t)`` holds; the
    last frame integrated, and the non-finite frame (-1 if none)."""
    T, dev = bc.shape[0], bc.device
    Z = torch.full((T, z0.shape[-1]), float("nan"), dtype=torch.float32, device=dev)
    Z[0], Z[1] = z0.to(dev, torch.float32), z1.to(dev, torch.float32)
    if correct is not None:  # the starting state too
        Z[0], Z[1] = correct(0, Z[0]), correct(1, Z[1])
    diverged = -1
    last = min(T, 2) - 1
    for t in range(2, T):
        zt = integrator(Z[t - 1 : t], Z[t - 2 : t - 1], bc[t : t + 1], bc[t - 1 : t], bc[t - 2 : t - 1])[0]
        last = t
        if not torch.isfinite(zt).all():
            Z[t] = zt
            diverged = t
            break
        Z[t] = zt if correct is None else correct(t, zt)
        if stop is not None and stop(t, Z[t]):
            break
    return Z, last, diverged


def past_extent(ae: Autoencoder, coords: RelativeCoordinates, z: torch.Tensor, xD, limit: float) -> bool:
    """Whether the latent z (r,) decodes, with the prescribed positions xD (m, 3), to a non-finite frame or one whose
    bounding-box diagonal exceeds ``limit`` by more than rounding (1e-6 of it): a diverged frame, past which a rollout
    whose steps are corrected (the contact projection fed back) stops instead of correcting frames that will be
    discarded.  The slack keeps the stop where the whole rollout's own test (decoded in one batch) also finds the frame
    diverged."""
    x = decode_latents(ae, coords, z[None], torch.as_tensor(xD)[None].to(z.device))[0]
    return not bool(torch.isfinite(x).all()) or float(_diagonal(x.double())) > limit * (1.0 + 1e-6)


def _diagonal(x: torch.Tensor) -> torch.Tensor:
    """Bounding-box diagonal of positions (..., n, 3) -> (...)."""
    return torch.linalg.vector_norm(x.amax(-2) - x.amin(-2), dim=-1)


def _first_bad_frame(X: torch.Tensor, max_extent: float | None, rest_positions) -> int:
    """The first frame of X (T, n, 3) with a non-finite position or (``max_extent`` given) a
    bounding-box diagonal over ``max_extent`` times that of ``rest_positions`` (else of X[0]);
    -1 if none."""
    bad = ~torch.isfinite(X).all(-1).all(-1)
    if max_extent is not None:
        ref = _diagonal(torch.as_tensor(rest_positions, dtype=torch.float64)) if rest_positions is not None else _diagonal(X[0])
        bad |= _diagonal(X) > float(max_extent) * float(ref)
    hits = torch.nonzero(bad).reshape(-1)
    return int(hits[0]) if hits.numel() else -1


def _energies(potential, coords: RelativeCoordinates, X: torch.Tensor, dirichlet_positions: torch.Tensor) -> dict:
    """Per-frame ``kinetic_energy`` (T,) (NaN at frame 0) and ``incremental_potential`` (T,)
    (NaN at frames 0, 1) of positions X (T, n, 3), on the CPU in float64."""
    T = X.shape[0]
    ke = torch.full((T,), float("nan"), dtype=torch.float64)
    ip = torch.full((T,), float("nan"), dtype=torch.float64)
    pot = potential_on(potential, torch.device("cpu"))
    if T > 1:
        ke[1:] = pot.kinetic_energy(X[1:], X[:-1])
    if T > 2:
        xD = dirichlet_positions.to("cpu", torch.float64)
        ip[2:] = pot(X[2:], X[1:-1], X[:-2], targets=xD[2:], penalty=not coords.hard_dirichlet)
    return {"kinetic_energy": ke, "incremental_potential": ip}

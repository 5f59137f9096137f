"""The latent integrator's loss (Li et al. 2025, sec. 3.3): the incremental potential of the
decoded prediction (Eq. 4), with training noise on the input latents (Eq. 5) and data
balancing by the previous step's mean velocity (Eq. 6); or the supervised L2 baseline.

:func:`integrator_loss`'s terms, for a minibatch (:class:`~latentsim.latent.batch.Batch`):

- Self-supervised (Eq. 4): the predicted latent is decoded (with the frame-t Dirichlet positions)
  and the loss is the incremental potential ``potential(x_t, x_{t-1}, x_{t-2}, targets=xD_t,
  penalty=use_penalty)``, x_{t-1}, x_{t-2} the *decoded* input latents (at each sample's time step
  ``dt`` and elastic factor ``stiffness`` where the batch gives them).  Supervised: the squared L2
  distance ``|z_pred - z_t|^2`` to the ground-truth latent.
- Training noise (Eq. 5, ``noise_scale > 0``): the batch is doubled with copies whose z_{t-1},
  z_{t-2} carry uniform noise in ``[-a, a]``, ``a = noise_scale * std`` (per latent dimension,
  over this batch, separately for z_{t-1} and z_{t-2}); BCs, Dirichlet targets (and the target
  z_t) unchanged (:func:`with_training_noise`).
- Data balancing (Eq. 6, ``balancing=True``): each sample's loss is multiplied by
  :func:`balancing_weights` of its decoded x_{t-1}, x_{t-2} (the perturbed ones for perturbed
  samples), or by the batch's ``balance`` computed beforehand; and by its ``scale``, if any.
- Supervision (``supervised_weight`` w > 0, self-supervised mode only; not in the paper): the loss
  gains ``w * mean_b |(z_pred_b - z_b) / sigma|^2`` over the unperturbed samples, sigma the
  integrator's output scale ``out_std`` (the spread of the training increments; 1 for a callable
  without one).  The incremental potential minimised in a small latent space is not the full-space
  dynamics projected into it; the term pulls the integrator towards the latter where the training
  data show it.

Physics is never re-implemented here: the energy is the scene's
:class:`latentsim.physics.incremental_potential.IncrementalPotential`, evaluated in float64 on
positions the autoencoder decodes.
"""

from __future__ import annotations

from typing import Callable

import torch

from latentsim.latent.autoencoder import Autoencoder, decode_latents
from latentsim.latent.batch import Batch, Triplets
from latentsim.latent.coordinates import RelativeCoordinates


def balancing_weights(x_prev: torch.Tensor, x_prev2: torch.Tensor, dt: float, eps: float = 1e-2) -> torch.Tensor:
    """Data-balancing weights 1 / max(|v_{t-1}|, eps) of paper Eq. 6.

    v_{t-1} = (1/N) sum_j (x_{t-1}^j - x_{t-2}^j) / dt is the mean full-space
    velocity (a 3-vector) of the previous step.  ``eps`` [m/s] keeps the weight
    finite for samples at rest (v = 0), capping it at 1/eps.

    x_prev, x_prev2 : (B, n, 3) -> (B,); dt : a float or (B,), each sample's time step.
    """
    if torch.is_tensor(dt) and dt.ndim:
        dt = dt.reshape(-1, 1, 1)
    v = ((x_prev - x_prev2) / dt).mean(-2)
    return 1.0 / torch.linalg.vector_norm(v, dim=-1).clamp_min(eps)


@torch.no_grad()
def fixed_balancing_weights(ae: Autoencoder, coords: RelativeCoordinates, data, dt: float, eps: float = 1e-2, chunk: int = 256) -> torch.Tensor:
    """:func:`balancing_weights` of every triplet of ``data`` (a :class:`~latentsim.latent.batch.Triplets`
    or a dict of its fields; its decoded ``z_prev``, ``z_prev2``), once.

    For a training whose inputs carry no noise and whose triplets do not change (the supervised baselines) the
    weights are the same every epoch; :func:`integrator_loss` takes them as the batch's ``balance`` instead of
    decoding two latents per sample in every minibatch.  Decoded ``chunk`` rows at a time (a decode's rows do not
    depend on each other)."""
    data = Triplets.of(data)
    out = []
    for a in range(0, data.z_prev.shape[0], chunk):
        rows = slice(a, a + chunk)
        x1 = decode_latents(ae, coords, data.z_prev[rows], data.xD_prev[rows])
        x2 = decode_latents(ae, coords, data.z_prev2[rows], data.xD_prev2[rows])
        out.append(balancing_weights(x1, x2, dt, eps))
    return torch.cat(out)


def integrator_loss(integrator: Callable, ae: Autoencoder, coords: RelativeCoordinates, potential, batch: Batch | dict, mode: str = "self_supervised",
                    noise_scale: float = 0.1, balancing: bool = True, use_penalty: bool | None = None, balancing_eps: float = 1e-2,
                    generator: torch.Generator | None = None, supervised_weight: float = 0.0):  # fmt: skip
    """Loss of one minibatch of triplets (the terms are described in the module's docstring).

    Parameters
    ----------
    integrator : maps (z_prev, z_prev2, p, p_prev, p_prev2) -> z (B, r).
    ae, coords : the autoencoder (frozen, eval mode expected) and its RelativeCoordinates.
    potential : IncrementalPotential (its ``dt`` is used for balancing where the batch has none).
    batch : :class:`~latentsim.latent.batch.Batch` of B rows (or a dict of its fields); its ``z``, the ground truth, is used
        by ``mode="supervised"`` and the supervision term; its optional ``dt``, ``stiffness`` and ``scale`` give each
        sample's condition, its ``balance`` the balancing weights computed beforehand (:func:`fixed_balancing_weights`;
        not with training noise, which would perturb the inputs).
    mode : 'self_supervised' (Eq. 4) or 'supervised' (L2 to the ground-truth latent).
    noise_scale : a of Eq. 5 in units of the batch's spread (0: no training noise).
    balancing : Eq. 6's weights; balancing_eps : their floor on the speed.
    use_penalty : Dirichlet penalty in the potential; ``None`` -> on unless
        ``coords.hard_dirichlet`` (rods: roots re-applied exactly on decode).
    generator : CPU generator for the noise.
    supervised_weight : w >= 0 of the supervision term (self-supervised mode only).

    Returns
    -------
    loss : scalar, mean over the (possibly doubled) batch of weight * per-sample loss (+ the
        supervision term).
    info : dict with ``per_sample`` (unweighted per-sample losses, (B',)),
        ``weights`` (B',), ``count`` B', ``prediction`` (B', r) (all detached).
    """
    if mode not in ("self_supervised", "supervised"):
        raise ValueError(f"mode must be 'self_supervised' or 'supervised', got {mode!r}")
    if supervised_weight < 0 or (supervised_weight > 0 and mode != "self_supervised"):
        raise ValueError(f"supervised_weight must be >= 0 and is for the self-supervised loss; got {supervised_weight} with mode {mode!r}")
    if use_penalty is None:
        use_penalty = not coords.hard_dirichlet
    batch = Batch.of(batch)
    clean = len(batch)
    fixed = batch.balance if balancing else None
    if noise_scale and noise_scale > 0:
        if fixed is not None:
            raise ValueError("balancing weights computed beforehand (batch['balance']) do not hold for inputs with training noise")
        batch = with_training_noise(batch, noise_scale, generator)
    pred = integrator(batch.z_prev, batch.z_prev2, batch.p, batch.p_prev, batch.p_prev2)
    x1 = x2 = None
    if mode == "self_supervised" or (balancing and fixed is None):
        with torch.no_grad():  # constants w.r.t. the integrator weights
            x1 = decode_latents(ae, coords, batch.z_prev, batch.xD_prev)
            x2 = decode_latents(ae, coords, batch.z_prev2, batch.xD_prev2)
    if mode == "self_supervised":
        x = decode_latents(ae, coords, pred, batch.xD)
        per = potential(x, x1, x2, targets=batch.xD.to(torch.float64), penalty=bool(use_penalty), dt=batch.dt, stiffness=batch.stiffness)
    else:
        if batch.z is None:
            raise ValueError("supervised loss needs the ground-truth latents batch['z']")
        per = ((pred - batch.z.to(pred)) ** 2).sum(-1).to(torch.float64)
    w = _sample_weights(batch, per, fixed, x1, x2, float(potential.dt), balancing_eps) if balancing else torch.ones_like(per)
    if batch.scale is not None:
        w = w * batch.scale.to(w)
    loss = (w * per).mean()
    if supervised_weight > 0:
        loss = loss + float(supervised_weight) * _supervision(integrator, pred, batch.z, clean).to(loss)
    info = {"per_sample": per.detach(), "weights": w.detach(), "count": len(batch), "prediction": pred.detach()}
    return loss, info


def _sample_weights(batch: Batch, per: torch.Tensor, fixed, x1, x2, dt: float, eps: float) -> torch.Tensor:
    """Eq. 6's weights of the samples, as ``per``'s dtype: those computed beforehand (``fixed``), or
    :func:`balancing_weights` of the decoded inputs ``x1``, ``x2`` at each sample's time step (the
    batch's ``dt``, else ``dt``)."""
    if fixed is not None:
        return fixed.to(per)
    return balancing_weights(x1, x2, dt if batch.dt is None else batch.dt.to(x1), eps).to(per)


def _supervision(integrator: Callable, pred: torch.Tensor, z, clean: int) -> torch.Tensor:
    """The supervision term's mean |(z_pred - z) / sigma|^2 over the first ``clean`` (unperturbed)
    samples, sigma the integrator's ``out_std`` (1 for a callable without one)."""
    if z is None:
        raise ValueError("supervised_weight needs the ground-truth latents batch['z']")
    scale = getattr(integrator, "out_std", None)
    scale = torch.ones_like(pred[0]) if scale is None else scale.to(pred)
    return (((pred[:clean] - z[:clean].to(pred)) / scale) ** 2).sum(-1).mean()


def with_training_noise(batch: Batch | dict, noise_scale: float, generator: torch.Generator | None = None) -> Batch:
    """The batch doubled with perturbed copies (paper Eq. 5): the copies' ``z_prev``, ``z_prev2``
    carry uniform noise in ``[-a, a]``, ``a = noise_scale * std`` (per latent dimension, over this
    batch, separately for each); every other field (BCs, Dirichlet targets, ``z``, a condition) is repeated.

    batch : :class:`~latentsim.latent.batch.Batch` of B rows (or a dict of its fields) -> 2B rows.
    generator : CPU generator of the noise (z_prev's first, then z_prev2's).
    """

    def noisy(z):
        a = noise_scale * z.std(0, unbiased=False)
        r = torch.rand(z.shape, generator=generator, dtype=z.dtype).to(z.device)
        return z + (2.0 * r - 1.0) * a

    batch = Batch.of(batch)
    z1n, z2n = noisy(batch.z_prev), noisy(batch.z_prev2)
    return batch.map(lambda v: torch.cat([v, v])).replace(z_prev=torch.cat([batch.z_prev, z1n]), z_prev2=torch.cat([batch.z_prev2, z2n]))

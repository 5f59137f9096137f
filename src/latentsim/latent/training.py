"""Training the latent integrator (Li et al. 2025, sec. 3.3): minibatch Adam on the loss of
:mod:`latentsim.latent.loss` over the ground-truth triplets of the training sequences, the
autoencoder frozen; with checkpoints that a killed training resumes from exactly.

:func:`fit_integrator` is the loop; its steps are the setup (frozen autoencoder, potential on the
device, triplets), the integrator's construction, one epoch, the learning-rate schedule and the
checkpoint (:func:`training_fingerprint` says which training a checkpoint belongs to).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import logging
import math
import os
import time
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from latentsim.config import with_defaults
from latentsim.latent.autoencoder import Autoencoder
from latentsim.latent.base import LossHealth, TrainingDiverged, minibatches, potential_on, resolve_device
from latentsim.latent.conditioning import CONDITION_DIM, AtCondition, Conditioning, with_condition
from latentsim.latent.coordinates import RelativeCoordinates
from latentsim.latent.data import build_triplets, triplet_rows
from latentsim.latent.integrator import LatentIntegrator, boundary_inputs
from latentsim.latent.loss import fixed_balancing_weights, integrator_loss
from latentsim.latent.serialization import atomic_save, load_checked
from latentsim.physics.kernels import with_compiled_elastic
from latentsim.scene import dirichlet_step, dirichlet_trajectory

log = logging.getLogger(__name__)


def training_fingerprint(cfg: dict, seed: int, hparams: dict, data: dict, ae: nn.Module, conditioning: Conditioning | None = None) -> str:
    """sha256 of what determines an integrator's training: its settings (without ``epochs`` at a
    constant learning rate, where a longer run continues a shorter one exactly), the seed, the
    architecture, the training triplets, the autoencoder's weights and the conditions trained over.
    A checkpoint resumes only a training with the same fingerprint."""
    drop = {"epochs"} if cfg["lr_final"] is None else set()
    what = {"cfg": {k: v for k, v in cfg.items() if k not in drop}, "seed": seed, "hparams": hparams}
    if conditioning is not None:
        what["conditioning"] = conditioning.to_dict()
    h = hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode())
    for name, t in [*sorted(data.items()), *ae.state_dict().items()]:
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def fit_integrator(
    ae: Autoencoder,
    coords: RelativeCoordinates,
    potential,
    sequences: Sequence[dict],
    config: dict | None = None,
    seed: int = 0,
    device="cpu",
    progress: bool = False,
    checkpoint_path: str | os.PathLike | None = None,
    checkpoint_every: int = 10,
    compiled: bool = True,
    label: str = "",
    conditioning: Conditioning | None = None,
):
    """Train a :class:`LatentIntegrator` on ground-truth triplets.

    Parameters
    ----------
    ae : trained autoencoder (a frozen, eval-mode copy is used).
    coords : RelativeCoordinates of the scene.
    potential : IncrementalPotential of the scene (the self-supervised loss).
    sequences : training sequences (see :func:`latentsim.latent.data.build_triplets`).
    config : settings of the config schema's ``integrator`` (widths, epochs, lr, lr_final (cosine
        decay of the learning rate to it; None: constant), batch_size, mode ('self_supervised' |
        'supervised'), noise_scale, supervised_weight, balancing, balancing_eps, use_penalty,
        residual, barrier_d_hat, barrier_kappa, barrier_extend_below (the loss's contact barrier,
        relative to the potential's), own_rollouts_every, own_rollouts_start, own_rollouts_speeds (see below), origin_input
        (each p_t ends with the frame's mean prescribed position, :func:`~latentsim.latent.integrator.boundary_inputs`;
        needs prescribed vertices, not with ``conditioning``), and the
        health rule's divergence_factor, max_loss, latent_range_factor); those
        absent take the schema's defaults (:func:`latentsim.config.with_defaults`).
    seed : seeds weight init, minibatch order and the training noise.
    checkpoint_path : when set, the integrator, optimiser, RNG state and history are saved every
        ``checkpoint_every`` epochs (and after the last) via a temp file and ``os.replace``; if
        the file exists at start and belongs to this training (:func:`training_fingerprint`:
        same settings, seed, architecture, training triplets and autoencoder; a run with more
        epochs may extend a shorter one at a constant learning rate), training resumes from it,
        else it starts over (logged) and overwrites it.  On CPU a resumed run is bitwise
        identical to an uninterrupted one.  The checkpoint also holds the training time so far,
        which the resumed run adds to its own (``history["train_seconds"]``).
    compiled : on the CPU, the loss's elastic energy runs the simulator's compiled
        kernels (``physics.kernels.with_compiled_elastic``: the same formulas, 5-8x
        faster than the batched PyTorch energy under autograd); False: the terms'
        PyTorch energies.
    label : what trains, for messages (e.g. "scene tiny_rods, method self_supervised").
    conditioning : None, or the box of time steps and moduli to train over
        (:mod:`latentsim.latent.conditioning`; self-supervised mode only, without supervision):
        each sample of each minibatch draws its condition from the box, its Dirichlet targets
        follow by the boundary-condition program at its time step, and its loss is the incremental
        potential at its condition, weighted by (h / h_0)^p (``time_step_weight_power`` p of the
        box: 2 makes the inertia term weigh the same at every time step, 0 weighs every time step
        alike).  A box of more than one point appends the normalised condition to each
        boundary-condition vector (``bc_dim`` + 2); a point trains an unconditioned integrator there.

    Own rollouts (``own_rollouts_every`` k > 0, self-supervised mode; not in the paper): from epoch
    ``own_rollouts_start`` on, every k epochs the integrator rolls out each training sequence in
    the latent space from its first two ground-truth latents, under its boundary conditions, until
    it ends or a latent leaves twice the training latents' radius; the triplets whose inputs are
    those rolled-out latents (with the frames' boundary conditions and Dirichlet targets) join the
    ground-truth ones until the next rollout.  The loss needs no ground truth at the predicted
    frame, so the integrator learns from the states it drifts into, in contact among them, and not
    only from those of the training data.  A conditioned training rolls each sequence out at a
    condition drawn from its box (:func:`own_rollout_triplets_at_conditions`), and those rows' loss
    is taken at that condition: states of conditions no training sequence was simulated at.
    With ``own_rollouts_speeds`` [lo, hi] each rollout of an unconditioned integrator also rolls each
    moving training sequence out once more under its program at a speed drawn from that range
    (:func:`own_rollout_triplets_at_speeds`): states of faster or slower motions than the data's.

    Returns
    -------
    integrator : trained, eval mode, on ``device``.
    history : ``loss`` (per-epoch mean weighted training loss; with own rollouts, of the data's
        triplets alone), ``latent_mse``
        (per-epoch mean |z_pred - z_t|^2 / r on the clean half of each
        batch), ``start_epoch`` (0, or the epoch resumed from), ``n_triplets``,
        ``loss_start``, ``loss_scale`` (:class:`~latentsim.latent.base.LossHealth`),
        ``latent_radius`` R and ``latent_distance`` (per epoch, the largest |z_pred - c|, see
        below), ``train_seconds`` (this call's time from its start, setup included, plus that
        of the run a checkpoint resumed, up to that checkpoint; time spent after the last
        checkpoint of a killed run is lost with its epochs); with own rollouts, ``own_triplets``
        (the rolled-out triplets of each rollout).

    Raises
    ------
    TrainingDiverged : naming ``label``, the epoch and the value, when a loss or gradient is not
        finite, or after an epoch that breaks the health rule:

        - its mean loss is far above the loss at the start or above ``max_loss``
          (:class:`~latentsim.latent.base.LossHealth`, ``divergence_factor``);
        - the latents leave the training range: some one-step prediction z_pred (from a clean,
          ground-truth input) lies farther than ``latent_range_factor`` R from the centre c of
          the training latents, where c is their mean and R the largest |z - c| over them.

        The epoch's checkpoint is then not written: the one on disk (if any) is the last good one.
    """
    t_start = time.perf_counter()
    cfg = with_defaults("integrator", config, "fit_integrator")
    if cfg["mode"] not in ("self_supervised", "supervised"):
        raise ValueError(f"mode must be 'self_supervised' or 'supervised', got {cfg['mode']!r}")
    if conditioning is not None and (cfg["mode"] != "self_supervised" or float(cfg["supervised_weight"]) > 0):
        raise ValueError(
            f"{label or 'integrator'}: a conditioned integrator trains on the incremental potential alone (mode self_supervised, "
            f"supervised_weight 0; got mode {cfg['mode']!r}, supervised_weight {cfg['supervised_weight']}): ground truth exists only "
            "at the conditions of the training sequences"
        )
    if conditioning is not None and cfg["origin_input"]:
        raise ValueError(f"{label or 'integrator'}: origin_input is not for a conditioned integrator (its own rollouts step the program at other time steps)")
    if conditioning is not None and coords.rigid:
        raise ValueError(f"{label or 'integrator'}: an autoencoder with rigid_frame is not for a conditioned integrator (its timing and own rollouts step the program in the world's frame)")
    if cfg["origin_input"] and any(np.shape(s["dirichlet_positions"])[-2] == 0 for s in sequences):
        raise ValueError(f"{label or 'integrator'}: origin_input needs prescribed vertices (a free body's latent is already where it is in the world)")
    own_every = int(cfg["own_rollouts_every"])
    if own_every > 0 and cfg["mode"] != "self_supervised":
        raise ValueError(f"{label or 'integrator'}: own_rollouts_every needs a self-supervised training")
    programs = _speed_programs(sequences, cfg, conditioning, label)
    device = resolve_device(device)
    ae_f, pot, data = _training_setup(ae, coords, potential, sequences, device, compiled, cfg)
    integ = _new_integrator(data, cfg, seed, device, conditioning)
    rows_per_sequence = triplet_rows(sequences)
    opt = torch.optim.Adam(integ.parameters(), lr=float(cfg["lr"]))
    gen = torch.Generator().manual_seed(seed)
    health = LossHealth(cfg["divergence_factor"], cfg["max_loss"], key="integrator")
    centre, radius = _latent_range(data["z"])
    history: dict[str, Any] = {"loss": [], "latent_mse": [], "latent_distance": [], "start_epoch": 0, "n_triplets": data["z"].shape[0], "latent_radius": radius}
    epochs, every = int(cfg["epochs"]), max(1, int(checkpoint_every))
    start, fingerprint, seconds_before = 0, None, 0.0
    if checkpoint_path is not None:
        fingerprint = training_fingerprint(cfg, seed, integ.hparams, data, ae_f, conditioning)
        start, seconds_before = _resume(checkpoint_path, fingerprint, epochs, integ, opt, gen, history, health)
    own = history.pop("own", None)  # a resumed run's rolled-out triplets
    if cfg["mode"] == "supervised" and not float(cfg["noise_scale"]) and cfg["balancing"] and conditioning is None:
        # inputs without noise that never change: Eq. 6's weights once, not two decodes a sample every minibatch
        data = dict(data, balance=fixed_balancing_weights(ae_f, coords, data, float(pot.dt), float(cfg["balancing_eps"])))
    bar = tqdm(range(start, epochs), desc="integrator", disable=not progress, leave=False)
    try:
        for epoch in bar:
            _set_learning_rate(opt, cfg, epoch, epochs)
            if own_every > 0 and epoch >= int(cfg["own_rollouts_start"]) and (epoch - int(cfg["own_rollouts_start"])) % own_every == 0:
                if conditioning is None:
                    own = own_rollout_triplets(integ, data, rows_per_sequence, centre, 2.0 * radius)
                    if programs is not None:
                        at_speeds = own_rollout_triplets_at_speeds(integ, data, rows_per_sequence, centre, 2.0 * radius, programs, cfg["own_rollouts_speeds"],
                                                                   gen, float(pot.dt), bool(cfg["origin_input"]), coords)  # fmt: skip
                        own = {key: torch.cat([val, at_speeds[key]]) for key, val in own.items()}
                else:
                    own = own_rollout_triplets_at_conditions(integ, data, rows_per_sequence, centre, 2.0 * radius, conditioning, gen)
                history.setdefault("own_triplets", []).append(int(own["z"].shape[0]))
            train_data = data if own is None else _with_own_rows(data, own)
            n_ground_truth = None if own is None else data["z"].shape[0]
            loss, mse, distance = _integrator_epoch(integ, opt, ae_f, coords, pot, train_data, cfg, gen, epoch, health, centre, conditioning, n_ground_truth)
            health.check(epoch, loss)
            _check_latent_range(epoch, distance, radius, float(cfg["latent_range_factor"]))
            history["loss"].append(loss)
            history["latent_mse"].append(mse)
            history["latent_distance"].append(distance)
            bar.set_postfix(loss=f"{history['loss'][-1]:.4e}")
            if checkpoint_path is not None and ((epoch + 1) % every == 0 or epoch + 1 == epochs):
                history.update(health.state())
                seconds = seconds_before + time.perf_counter() - t_start
                _save_checkpoint(checkpoint_path, fingerprint, seed, epoch + 1, integ, opt, gen, history, seconds, own)
    except TrainingDiverged as e:
        e.label = e.label or label
        raise
    history.update(health.state())
    history["train_seconds"] = seconds_before + time.perf_counter() - t_start
    integ.eval()
    return integ, history


def _latent_range(z: torch.Tensor) -> tuple[torch.Tensor, float]:
    """The centre c (r,) of the training latents z (N, r), their mean, and the radius R of the range,
    the largest |z - c|."""
    centre = z.mean(0)
    return centre, float((z - centre).norm(dim=-1).max()) if z.shape[0] else 0.0


def _check_latent_range(epoch: int, distance: float, radius: float, factor: float) -> None:
    """Raise TrainingDiverged when the 0-based ``epoch``'s largest |z_pred - c| exceeds
    ``factor`` times the training range's radius R (a range of radius 0, a single latent, is not
    checked)."""
    if radius > 0 and not distance <= factor * radius:
        raise TrainingDiverged(
            epoch + 1, value=distance,
            detail=(f"the predicted latents leave the training range: a one-step prediction lies {distance:.4g} from the training "
                    f"latents' centre, {distance / radius:.3g} times their radius {radius:.4g} (integrator.latent_range_factor = {factor:g})"),
        )  # fmt: skip


def _training_setup(ae: Autoencoder, coords: RelativeCoordinates, potential, sequences: Sequence[dict], device: torch.device, compiled: bool, cfg: dict):
    """A frozen eval-mode copy of the autoencoder on ``device``, the potential there (its elastic
    energy on the compiled kernels where ``compiled`` and on the CPU; its contact barrier, if any,
    the learned loss's of ``cfg``'s ``barrier_*`` settings, extended finitely past the colliders'
    surfaces), and the training triplets."""
    ae_f = copy.deepcopy(ae).to(device).eval()
    ae_f.requires_grad_(False)
    pot = potential_on(potential, device)
    if getattr(pot, "contact", None) is not None:  # finite past the colliders' surfaces: a decode that enters one costs much, not inf
        barrier = pot.contact.extended(cfg["barrier_extend_below"], cfg["barrier_d_hat"], cfg["barrier_kappa"])
        pot = dataclasses.replace(pot, contact=barrier)
    if compiled and device.type == "cpu":
        pot = with_compiled_elastic(pot)
    return ae_f, pot, build_triplets(ae_f, coords, sequences, origin=bool(cfg["origin_input"]))


@torch.no_grad()
def own_rollout_triplets(integ: LatentIntegrator, data: dict, rows_per_sequence: Sequence[int], centre: torch.Tensor, max_distance: float) -> dict:
    """Triplets whose inputs are the integrator's own latents: each training sequence of ``data``
    (:func:`~latentsim.latent.data.build_triplets`: ``rows_per_sequence[i]`` rows of sequence i,
    in order) rolled out from its first two ground-truth latents under its boundary conditions,
    until it ends or a latent lies farther than ``max_distance`` from ``centre``.  Each row keeps
    the frame's boundary conditions, Dirichlet targets and ground-truth latent ``z``; its
    ``z_prev`` and ``z_prev2`` are the rolled-out ones (a sequence's first row keeps its ground
    truth: it is the first step).  The training mode of ``integ`` is restored."""
    if sum(rows_per_sequence) != data["z"].shape[0]:
        raise ValueError(f"rows_per_sequence sums to {sum(rows_per_sequence)}, the triplets have {data['z'].shape[0]} rows")
    was_training = integ.training
    integ.eval()
    ends = np.cumsum(rows_per_sequence).tolist()
    starts = [0] + ends[:-1]
    rows, z_prev, z_prev2 = [], [], []
    for a, b in zip(starts, ends):
        z2, z1 = data["z_prev2"][a], data["z_prev"][a]
        for i in range(a, b):
            rows.append(i)
            z_prev.append(z1)
            z_prev2.append(z2)
            z = integ(z1[None], z2[None], data["p"][i : i + 1], data["p_prev"][i : i + 1], data["p_prev2"][i : i + 1])[0].to(z1.dtype)
            if not torch.isfinite(z).all() or float((z - centre).norm()) > max_distance:
                break
            z2, z1 = z1, z
    if was_training:
        integ.train()
    idx = torch.as_tensor(rows, device=data["z"].device)
    own = {key: val[idx] for key, val in data.items()}
    own["z_prev"], own["z_prev2"] = torch.stack(z_prev), torch.stack(z_prev2)
    return own


@torch.no_grad()
def own_rollout_triplets_at_conditions(
    integ: LatentIntegrator, data: dict, rows_per_sequence: Sequence[int], centre: torch.Tensor, max_distance: float, conditioning: Conditioning, gen: torch.Generator,
) -> dict:  # fmt: skip
    """:func:`own_rollout_triplets` of a conditioned integrator: each training sequence rolled out at
    one condition (h, E) drawn from ``conditioning``'s box by ``gen``, its boundary-condition program
    (the frames' p_t) stepped at h from the sequence's first Dirichlet positions.  Each row holds
    the Dirichlet targets of its frames at h and its ``condition`` (h, E) (float64, (N, 2)), at
    which its loss is to be taken (:func:`_at_sampled_conditions`)."""
    ends = np.cumsum(rows_per_sequence).tolist()
    h, E = conditioning.sample(len(ends), gen)
    parts = []
    for a, b, hi, Ei in zip([0] + ends[:-1], ends, h.tolist(), E.tolist()):
        sub = {key: val[a:b] for key, val in data.items()}
        at = AtCondition(integ, conditioning.normalise(hi, Ei)).to(data["z"].device) if conditioning.conditioned else integ
        own = own_rollout_triplets(at, sub, [b - a], centre, max_distance)
        n = own["z"].shape[0]
        p = torch.cat([sub["p_prev2"][:1], sub["p_prev"][:1], sub["p"][: n]])  # frames 0 .. n + 1
        xD = [sub["xD_prev2"][0]]
        for t in range(1, n + 2):
            xD.append(dirichlet_step(xD[-1][None], p[t : t + 1], hi)[0])
        xD = torch.stack(xD)
        own["xD_prev2"], own["xD_prev"], own["xD"] = xD[:n], xD[1 : n + 1], xD[2:]
        own["condition"] = torch.tensor([hi, Ei], dtype=torch.float64, device=xD.device).expand(n, 2).clone()
        parts.append(own)
    return {key: torch.cat([q[key] for q in parts]) for key in parts[0]}


def _speed_programs(sequences: Sequence[dict], cfg: dict, conditioning: Conditioning | None, label: str) -> list | None:
    """What ``own_rollouts_speeds`` scales: for each training sequence that gives triplets (in
    :func:`~latentsim.latent.data.triplet_rows`' order), its boundary-condition program (T, 6)
    (float64; None where the program is still, a free body: no speed to scale) and its first frame's
    prescribed positions (m, 3); None where the setting is not given.  Raises ValueError, naming the
    key, where it cannot apply."""
    speeds = cfg["own_rollouts_speeds"]
    if speeds is None:
        return None
    what = f"{label or 'integrator'}: integrator.own_rollouts_speeds"
    if int(cfg["own_rollouts_every"]) <= 0:
        raise ValueError(f"{what} scales the own rollouts' programs, but there are none (own_rollouts_every is 0)")
    if conditioning is not None:
        raise ValueError(f"{what} is not for a conditioned integrator (its own rollouts are drawn at conditions of its box)")
    if float(cfg["supervised_weight"]) > 0:
        raise ValueError(f"{what} is not for a training with a supervised term (supervised_weight {cfg['supervised_weight']}): "
                         "ground truth exists only at the recorded speeds")  # fmt: skip
    lo, hi = (float(v) for v in speeds)
    if not 0 < lo <= hi:
        raise ValueError(f"{what} must be [lo, hi] with 0 < lo <= hi, got {list(speeds)}")
    programs = []
    for s in sequences:
        if len(s["positions"]) < 3:
            continue
        bc = np.asarray(s.get("bc", np.zeros((len(s["positions"]), 0))), dtype=np.float64)
        if bc.ndim != 2 or bc.shape[1] != 6:
            raise ValueError(f"{what} scales a boundary-condition program of 6 numbers a frame (velocity, angular velocity); got shape {bc.shape}")
        programs.append((bc if bc.any() else None, np.asarray(s["dirichlet_positions"], dtype=np.float64)[0]))
    if all(bc is None for bc, _ in programs):
        raise ValueError(f"{what}: no training sequence has a program to scale (all are still: a free body's)")
    return programs


@torch.no_grad()
def own_rollout_triplets_at_speeds(
    integ: LatentIntegrator, data: dict, rows_per_sequence: Sequence[int], centre: torch.Tensor, max_distance: float, programs: Sequence, speeds,
    gen: torch.Generator, dt: float, origin: bool, coords: RelativeCoordinates | None = None,
) -> dict:  # fmt: skip
    """:func:`own_rollout_triplets` under faster or slower programs: each training sequence whose
    program moves (``programs``, :func:`_speed_programs`) rolled out from its first two ground-truth
    latents under its program with every velocity and angular velocity scaled by a factor f drawn by
    ``gen`` log-uniformly from ``speeds`` = [lo, hi], its prescribed positions stepped from its first
    frame's by the scaled program at the time step ``dt`` (:func:`~latentsim.scene.dirichlet_trajectory`),
    and the integrator's inputs made of them (:func:`~latentsim.latent.integrator.boundary_inputs`,
    ``origin`` and ``coords`` as in the training).  Each row holds the frame's Dirichlet targets
    under the scaled program (the self-supervised loss needs nothing else there); its ``z`` is the
    recorded frame's, as no ground truth exists at other speeds.  Also returns ``speed`` (N,), each
    row's factor."""
    lo, hi = (math.log(float(v)) for v in speeds)
    ends = np.cumsum(rows_per_sequence).tolist()
    factors = torch.exp(lo + (hi - lo) * torch.rand(len(ends), generator=gen, dtype=torch.float64)).tolist()
    parts = []
    for a, b, (bc, xD0), f in zip([0] + ends[:-1], ends, programs, factors):
        if bc is None:
            continue
        sub = {key: val[a:b] for key, val in data.items()}
        xD = dirichlet_trajectory(xD0, f * bc, dt)
        p = torch.as_tensor(boundary_inputs(f * bc, xD, origin, coords)).to(sub["p"])
        xD = torch.as_tensor(xD).to(sub["xD"])
        for key, arr in (("p", p), ("xD", xD)):
            sub[key], sub[key + "_prev"], sub[key + "_prev2"] = arr[2:], arr[1:-1], arr[:-2]
        own = own_rollout_triplets(integ, sub, [b - a], centre, max_distance)
        own["speed"] = torch.full((own["z"].shape[0],), f, dtype=torch.float64, device=own["z"].device)
        parts.append(own)
    return {key: torch.cat([q[key] for q in parts]) for key in parts[0]}


def _with_own_rows(data: dict, own: dict) -> dict:
    """The ground-truth triplets and the rolled-out ones in one set; where the rolled-out rows carry
    a ``condition``, the ground-truth rows get NaN there (a condition drawn per sample)."""
    out = {key: torch.cat([val, own[key]]) for key, val in data.items()}
    if "condition" in own:
        nan = torch.full((data["z"].shape[0], 2), float("nan"), dtype=own["condition"].dtype, device=own["condition"].device)
        out["condition"] = torch.cat([nan, own["condition"]])
    return out


def _new_integrator(data: dict, cfg: dict, seed: int, device: torch.device, conditioning: Conditioning | None = None) -> LatentIntegrator:
    """An untrained integrator of settings ``cfg`` (weights seeded by ``seed``), normalised by the
    statistics of the triplets ``data`` (a conditioned one's conditions by those of one draw from
    its box per triplet), on ``device``."""
    conditioned = conditioning is not None and conditioning.conditioned
    r, k = data["z"].shape[1], data["p"].shape[1] + (CONDITION_DIM if conditioned else 0)
    fork = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=fork):
        torch.manual_seed(seed)
        integ = LatentIntegrator(r, k, cfg["widths"], residual=bool(cfg["residual"]), origin=bool(cfg["origin_input"]))
    stats = {key: data[key].cpu() for key in ("z", "z_prev", "z_prev2", "p", "p_prev", "p_prev2")}
    if conditioned:
        c = conditioning.normalise(*conditioning.sample(stats["z"].shape[0], torch.Generator().manual_seed(seed)))
        for key in ("p", "p_prev", "p_prev2"):
            stats[key] = with_condition(stats[key], c)
    integ.fit_normalization(*stats.values())
    return integ.to(device)


def _at_sampled_conditions(batch: dict, conditioning: Conditioning, gen: torch.Generator) -> dict:
    """The minibatch with a condition drawn for each sample (:class:`Conditioning`; a row with a
    finite ``condition`` (h, E), rolled out at it, keeps it): its time step
    ``dt``, elastic factor ``stiffness`` and weight ``scale`` (:meth:`Conditioning.weight`), the frame-t Dirichlet
    targets that the boundary-condition program gives at its time step, and (for a conditioned
    integrator) the normalised condition appended to each boundary-condition vector."""
    h, E = conditioning.sample(batch["z"].shape[0], gen)
    out = dict(batch)
    fixed = out.pop("condition", None)
    if fixed is not None:  # a rolled-out row keeps the condition it was rolled out at
        keep = torch.isfinite(fixed[:, 0]).cpu()
        h = torch.where(keep, fixed[:, 0].cpu().to(h.dtype), h)
        E = torch.where(keep, fixed[:, 1].cpu().to(E.dtype), E)
    dev = batch["xD"].device
    out["dt"] = h.to(dev)
    out["stiffness"] = (E / conditioning.base_modulus).to(dev)
    out["scale"] = conditioning.weight(h).to(dev)
    out["xD"] = dirichlet_step(batch["xD_prev"], batch["p"], out["dt"])
    if conditioning.conditioned:
        c = conditioning.normalise(h, E).to(dev)
        for key in ("p", "p_prev", "p_prev2"):
            out[key] = with_condition(batch[key], c)
    return out


def _set_learning_rate(opt, cfg: dict, epoch: int, epochs: int) -> None:
    """With ``lr_final`` set, the cosine decay from ``lr`` to it: a function of the epoch alone (a
    resumed run gets the same rates); else the constant ``lr`` the optimiser holds."""
    if cfg["lr_final"] is not None:
        lr0, lr1 = float(cfg["lr"]), float(cfg["lr_final"])
        for group in opt.param_groups:
            group["lr"] = lr1 + 0.5 * (lr0 - lr1) * (1.0 + math.cos(math.pi * epoch / epochs))


def _integrator_epoch(
    integ: LatentIntegrator, opt, ae: Autoencoder, coords: RelativeCoordinates, pot, data: dict, cfg: dict, gen: torch.Generator, epoch: int,
    health: LossHealth, centre: torch.Tensor, conditioning: Conditioning | None = None, n_ground_truth: int | None = None,
):  # fmt: skip
    """One epoch of Adam over the triplets ``data`` in minibatches; the mean weighted loss, the
    mean latent MSE on the clean samples (against the training sequences' latents, which for a
    conditioned training are those of another condition), and the largest distance
    |z_pred - centre| of a clean sample's prediction from a ground-truth input (the first
    ``n_ground_truth`` rows; all when None).  The first minibatch of a training sets
    ``health``'s start and scale."""
    integ.train()
    tot, mse, cnt, count, distance = 0.0, 0.0, 0, 0, 0.0
    for b, idx in enumerate(minibatches(data["z"].shape[0], int(cfg["batch_size"]), gen)):
        idx = idx.to(data["z"].device)
        batch = {key: val[idx] for key, val in data.items()}
        if conditioning is not None:
            batch = _at_sampled_conditions(batch, conditioning, gen)
        loss, info = integrator_loss(
            integ, ae, coords, pot, batch,
            mode=cfg["mode"], noise_scale=float(cfg["noise_scale"]), balancing=bool(cfg["balancing"]),
            use_penalty=cfg["use_penalty"], balancing_eps=float(cfg["balancing_eps"]), generator=gen,
            supervised_weight=float(cfg["supervised_weight"]),
        )  # fmt: skip
        if not torch.isfinite(loss):
            raise TrainingDiverged(epoch + 1, b)
        weighted = info["per_sample"] * info["weights"]
        value = float(loss.detach())
        if n_ground_truth is not None:  # the health rule and history follow the ground-truth rows' loss alone
            weighted = weighted[(idx < n_ground_truth).repeat(weighted.shape[0] // idx.numel())]
            value = float(weighted.mean()) if weighted.numel() else float("nan")
        if weighted.numel():
            health.first_batch(value, weighted)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if any(q.grad is not None and not torch.isfinite(q.grad).all() for q in integ.parameters()):
            raise TrainingDiverged(epoch + 1, b, what="gradient")
        opt.step()
        nb = idx.numel()
        if n_ground_truth is None:
            tot, count = tot + value * nb, count + nb
        else:
            tot, count = tot + float(weighted.sum()), count + weighted.numel()
        mse += float(((info["prediction"][:nb] - batch["z"]) ** 2).mean()) * nb
        clean = info["prediction"][:nb] if n_ground_truth is None else info["prediction"][:nb][idx < n_ground_truth]
        if clean.shape[0]:
            distance = max(distance, float((clean - centre).norm(dim=-1).max()))
        cnt += nb
    return tot / count, mse / cnt, distance


def _resume(path, fingerprint: str, epochs: int, integ: LatentIntegrator, opt, gen: torch.Generator, history: dict, health: LossHealth) -> tuple[int, float]:
    """Load the checkpoint at ``path`` into the integrator, optimiser, generator, history and health
    rule when it belongs to this training (same fingerprint, no more than ``epochs`` done); the
    epoch to start from and the training time it records (0, 0.0 when there is none or it belongs
    to another training)."""
    if not os.path.exists(path):
        return 0, 0.0
    state = load_checked(path)
    if state.get("fingerprint") != fingerprint or int(state["epoch"]) > epochs:
        log.warning("checkpoint %s belongs to another training (settings, seed, architecture, data or a longer run): starting over", path)
        return 0, 0.0
    integ.load_state_dict(state["model"])
    opt.load_state_dict(state["optimizer"])
    gen.set_state(state["generator"])
    history["loss"] = list(state["history"]["loss"])
    history["latent_mse"] = list(state["history"]["latent_mse"])
    history["latent_distance"] = list(state["history"]["latent_distance"])
    health.load(state["history"])
    history["start_epoch"] = int(state["epoch"])
    if state.get("own") is not None:
        history["own"] = {k: v.to(integ.in_mean.device) for k, v in state["own"].items()}
        history["own_triplets"] = list(state.get("own_triplets", []))
    log.info("resuming %s at epoch %d (%.1f s of training so far)", path, history["start_epoch"], float(state["train_seconds"]))
    return history["start_epoch"], float(state["train_seconds"])


def _save_checkpoint(
    path, fingerprint: str, seed: int, epoch_done: int, integ: LatentIntegrator, opt, gen: torch.Generator, history: dict, seconds: float, own: dict | None = None,
) -> None:  # fmt: skip
    """Write the state after ``epoch_done`` epochs, the training time so far ``seconds`` and the
    rolled-out triplets ``own`` in use, atomically (the last good one stays on disk until the new
    one is complete)."""
    atomic_save(
        {
            "epoch": epoch_done,
            "fingerprint": fingerprint,
            "seed": seed,
            "hparams": integ.hparams,
            "model": integ.state_dict(),
            "optimizer": opt.state_dict(),
            "generator": gen.get_state(),
            "history": {k: history[k] for k in ("loss", "latent_mse", "latent_distance", "loss_start", "loss_scale")},
            "train_seconds": float(seconds),
            "own": None if own is None else {k: v.cpu() for k, v in own.items()},
            "own_triplets": list(history.get("own_triplets", [])),
        },
        path,
    )

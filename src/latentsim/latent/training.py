"""Training the latent integrator (Li et al. 2025, sec. 3.3): minibatch Adam on the loss of
:mod:`latentsim.latent.loss` over the ground-truth triplets of the training sequences, the
autoencoder frozen; with checkpoints that a killed training resumes from exactly.

:func:`fit_integrator` is the one loop: the setup (frozen autoencoder, potential on the device,
triplets), the integrator's construction, the epochs (:func:`_integrator_epoch`), the learning-rate
schedule and the checkpoint (:func:`training_fingerprint` says which training a checkpoint belongs
to).  The features beyond the paper are pieces it consumes (:mod:`latentsim.latent.features`):

- Conditioning (``conditioning``, a box of time steps and moduli, :mod:`latentsim.latent.conditioning`;
  self-supervised mode only, without supervision): each sample of each minibatch draws its
  condition from the box, its Dirichlet targets follow by the boundary-condition program at its
  time step, and its loss is the incremental potential at its condition, weighted by (h / h_0)^p
  (``time_step_weight_power`` p of the box: 2 makes the inertia term weigh the same at every time
  step, 0 weighs every time step alike).  A box of more than one point appends the normalised
  condition to each boundary-condition vector (``bc_dim`` + 2); a point trains an unconditioned
  integrator there.
- Own rollouts (``own_rollouts_every`` k > 0, self-supervised mode; not in the paper): from epoch
  ``own_rollouts_start`` on, every k epochs the integrator rolls out each training sequence in the
  latent space from its first two ground-truth latents, under its boundary conditions, until it
  ends, a latent leaves twice the training latents' radius or (a scene with contact) a latent
  decodes to a state with some point of the surface deep inside a collider or into the surface
  itself (:class:`~latentsim.latent.features.ClearStates`: deeper than 5% of the training states'
  diagonal, by the measure of the evaluation); the
  triplets whose inputs are those rolled-out latents (with the frames' boundary conditions and
  Dirichlet targets) join the ground-truth ones until the next rollout.  The loss needs no ground truth at the predicted frame,
  so the integrator learns from the states it drifts into, in contact among them, and not only
  from those of the training data.  A conditioned training rolls each sequence out at a condition
  drawn from its box, and those rows' loss is taken at that condition: states of conditions no
  training sequence was simulated at.  With ``own_rollouts_speeds`` [lo, hi] each rollout of an
  unconditioned integrator also rolls each moving training sequence out once more under its
  program at a speed drawn from that range: states of faster or slower motions than the data's.
  The health rule and the loss history follow the data's triplets alone.
- Plateau stop (``plateau_stop``; supervised mode only, :class:`~latentsim.latent.base.PlateauStop`): the
  training ends before an epoch once the least loss of the last ``window`` epochs is not ``tolerance``
  (relative) below the least before them; the rest of the epochs are not run.
- Origin input (``origin_input``): each p_t ends with the frame's mean prescribed position
  (:func:`~latentsim.latent.integrator.boundary_inputs`; needs prescribed vertices, not with
  ``conditioning``).

Health (raising :class:`~latentsim.latent.base.TrainingDiverged`, naming the label, the epoch and
the value): a loss or gradient that is not finite, or an epoch whose mean loss is far above the
loss at the start or above ``max_loss`` (:class:`~latentsim.latent.base.LossHealth`,
``divergence_factor``), or whose one-step predictions z_pred (from clean, ground-truth inputs) leave
the training range: some lies farther than ``latent_range_factor`` R from the centre c of the
training latents, c their mean and R the largest |z - c| over them.  The epoch's checkpoint is
then not written: the one on disk (if any) is the last good one.
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

import torch
from torch import nn
from tqdm import tqdm

from latentsim.config import with_defaults
from latentsim.latent.autoencoder import Autoencoder
from latentsim.latent.base import LossHealth, PlateauStop, TrainingDiverged, minibatches, potential_on, resolve_device
from latentsim.latent.batch import Triplets
from latentsim.latent.conditioning import Conditioning
from latentsim.latent.coordinates import RelativeCoordinates
from latentsim.latent.data import build_triplets
from latentsim.latent.features import ClearStates, TrainingFeatures, training_features
from latentsim.latent.integrator import LatentIntegrator
from latentsim.latent.loss import integrator_loss
from latentsim.latent.serialization import atomic_save, load_checked
from latentsim.physics.kernels import with_compiled_elastic

log = logging.getLogger(__name__)


def training_fingerprint(cfg: dict, seed: int, hparams: dict, data, ae: nn.Module, conditioning: Conditioning | None = None) -> str:
    """sha256 of what determines an integrator's training: its settings (without ``epochs`` at a
    constant learning rate, where a longer run continues a shorter one exactly), the seed, the
    architecture, the training triplets (:class:`~latentsim.latent.batch.Triplets` or a dict of
    its fields), the autoencoder's weights and the conditions trained over.  A checkpoint resumes
    only a training with the same fingerprint."""
    drop = {"epochs"} if cfg["lr_final"] is None else set()
    what = {"cfg": {k: v for k, v in cfg.items() if k not in drop}, "seed": seed, "hparams": hparams}
    if conditioning is not None:
        what["conditioning"] = conditioning.to_dict()
    h = hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode())
    for name, t in [*sorted(Triplets.of(data).fields().items()), *ae.state_dict().items()]:
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


@dataclasses.dataclass
class _Training:
    """What the epochs of one training work with (:func:`_new_training`).

    Attributes
    ----------
    integ, opt, gen, health : the integrator, its Adam, the generator of every draw and the health rule.
    plateau : the rule that ends a supervised training whose loss stopped falling, or None.
    ae, coords, pot, cfg : the frozen autoencoder, its coordinates, the loss's potential and the settings.
    features : the pieces of the features beyond the paper (:class:`~latentsim.latent.features.TrainingFeatures`).
    centre : the training latents' centre c.
    clear : which latents decode clear of the scene's colliders and of the surface itself, where the own rollouts stop
        (:class:`~latentsim.latent.features.ClearStates`), or None (no contact).
    """

    integ: LatentIntegrator
    opt: torch.optim.Optimizer
    gen: torch.Generator
    health: LossHealth
    ae: Autoencoder
    coords: RelativeCoordinates
    pot: Any
    cfg: dict
    features: TrainingFeatures
    centre: torch.Tensor
    plateau: PlateauStop | None = None
    clear: ClearStates | None = None


def _plateau_reached(run: _Training, losses, label: str) -> bool:
    """Whether the training ends here by its plateau rule (logged), before training another epoch."""
    if run.plateau is None or not run.plateau.reached(losses):
        return False
    p = run.plateau
    log.info("integrator%s: loss plateau after %d epochs (least loss of the last %d not %g below the least before): stopped",
                f" ({label})" if label else "", len(losses), p.window, p.tolerance)  # fmt: skip
    return True


def _own_rows(run: _Training, epoch: int, data, radius: float, own, history: dict):
    """The rolled-out rows epoch ``epoch`` trains on beside the data's: fresh ones where a rollout is
    due (their count appended to ``history["own_triplets"]``), else ``own``, the last ones (or None)."""
    fresh = run.features.rollouts(epoch, run.integ, data, run.centre, 2.0 * radius, run.gen, run.clear)
    if fresh is None:
        return own
    history.setdefault("own_triplets", []).append(len(fresh))
    return fresh


def fit_integrator(ae: Autoencoder, coords: RelativeCoordinates, potential, sequences: Sequence[dict], config: dict | None = None, seed: int = 0,
                   device="cpu", progress: bool = False, checkpoint_path: str | os.PathLike | None = None, checkpoint_every: int = 10,
                   compiled: bool = True, label: str = "", conditioning: Conditioning | None = None):  # fmt: skip
    """Train a :class:`LatentIntegrator` on ground-truth triplets (its features and health rule: the module's docstring).

    Parameters
    ----------
    ae, coords : the trained autoencoder (a frozen, eval-mode copy is used) and its RelativeCoordinates.
    potential, sequences : the scene's IncrementalPotential (the loss) and training sequences (:func:`~latentsim.latent.data.build_triplets`).
    config : the schema's ``integrator`` settings; those absent take its defaults (:func:`latentsim.config.with_defaults`).
    seed : seeds weight init, minibatch order, the training noise and the features' draws.
    checkpoint_path : when set, the integrator, optimiser, RNG state, history and rolled-out triplets are saved every ``checkpoint_every``
        epochs (and after the last) atomically; a file there of this training (:func:`training_fingerprint`; a run with more epochs
        may extend a shorter one at a constant learning rate) is resumed from, bitwise identically on the CPU, else overwritten (logged).
    compiled : on the CPU, the loss's elastic energy on the simulator's compiled kernels (``physics.kernels.with_compiled_elastic``).
    label, conditioning : what trains, for messages (e.g. "scene tiny_rods, method self_supervised"); the box of time steps
        and moduli to train over, or None.

    Returns
    -------
    integrator : trained, eval mode, on ``device``.
    history : per epoch ``loss`` (the data's triplets' mean weighted loss), ``latent_mse`` (mean |z_pred - z_t|^2 / r on the
        clean half of each batch) and ``latent_distance`` (the largest |z_pred - c|); ``start_epoch``, ``n_triplets``,
        ``loss_start``, ``loss_scale``, ``latent_radius`` R, ``train_seconds`` (setup included, plus a resumed run's up to
        its checkpoint); with own rollouts ``own_triplets``.
    """
    t_start = time.perf_counter()
    cfg = with_defaults("integrator", config, "fit_integrator")
    run, data, radius, history = _new_training(ae, coords, potential, sequences, cfg, seed, resolve_device(device), compiled, conditioning, label)
    epochs, every = int(cfg["epochs"]), max(1, int(checkpoint_every))
    fingerprint = None if checkpoint_path is None else training_fingerprint(cfg, seed, run.integ.hparams, data, run.ae, conditioning)
    start, seconds_before = (0, 0.0) if checkpoint_path is None else _resume(checkpoint_path, fingerprint, epochs, run, history)
    own = history.pop("own", None)  # a resumed run's rolled-out triplets
    data = run.features.prepared(data, run.ae, coords, float(run.pot.dt))
    bar = tqdm(range(start, epochs), desc="integrator", disable=not progress, leave=False)
    try:
        for epoch in bar:
            _set_learning_rate(run.opt, cfg, epoch, epochs)
            if _plateau_reached(run, history["loss"], label):
                break
            own = _own_rows(run, epoch, data, radius, own, history)
            loss, mse, distance = _integrator_epoch(run, data if own is None else data.cat(own), epoch, None if own is None else len(data))
            run.health.check(epoch, loss)
            _check_latent_range(epoch, distance, radius, float(cfg["latent_range_factor"]))
            for key, value in (("loss", loss), ("latent_mse", mse), ("latent_distance", distance)):
                history[key].append(value)
            bar.set_postfix(loss=f"{loss:.4e}")
            if checkpoint_path is not None and ((epoch + 1) % every == 0 or epoch + 1 == epochs):
                history.update(run.health.state())
                seconds = seconds_before + time.perf_counter() - t_start
                _save_checkpoint(checkpoint_path, fingerprint, seed, epoch + 1, run, history, seconds, own)
    except TrainingDiverged as e:
        e.label = e.label or label
        raise
    history.update(run.health.state())
    history["train_seconds"] = seconds_before + time.perf_counter() - t_start
    run.integ.eval()
    return run.integ, history


def _new_training(ae: Autoencoder, coords: RelativeCoordinates, potential, sequences: Sequence[dict], cfg: dict, seed: int, device: torch.device,
                  compiled: bool, conditioning: Conditioning | None, label: str):  # fmt: skip
    """The start of a training of settings ``cfg``: its :class:`_Training` (the features' pieces,
    checked, :func:`~latentsim.latent.features.training_features`; the frozen autoencoder, the
    potential, an untrained integrator, Adam, the generator seeded by ``seed``, the health rule
    and the training latents' centre), the ground truth's triplets, the range's radius and an
    empty history."""
    features = training_features(cfg, sequences, coords, float(potential.dt), conditioning, label)
    ae_f, pot, data = _training_setup(ae, coords, potential, sequences, device, compiled, cfg)
    integ = _new_integrator(data, cfg, seed, device, features)
    opt = torch.optim.Adam(integ.parameters(), lr=float(cfg["lr"]))
    gen = torch.Generator().manual_seed(seed)
    health = LossHealth(cfg["divergence_factor"], cfg["max_loss"], key="integrator")
    centre, radius = _latent_range(data.z)
    history: dict[str, Any] = {"loss": [], "latent_mse": [], "latent_distance": [], "start_epoch": 0, "n_triplets": len(data), "latent_radius": radius}
    plateau = PlateauStop.of(cfg["plateau_stop"])
    # the simulator's barrier, not the extended one
    clear = ClearStates.of(ae_f, coords, getattr(potential, "contact", None), sequences) if features.own is not None else None
    return _Training(integ, opt, gen, health, ae_f, coords, pot, cfg, features, centre, plateau, clear), data, radius, history


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
    surfaces), and the training triplets (:class:`~latentsim.latent.batch.Triplets`)."""
    ae_f = copy.deepcopy(ae).to(device).eval()
    ae_f.requires_grad_(False)
    pot = potential_on(potential, device)
    if getattr(pot, "contact", None) is not None:  # finite past the colliders' surfaces: a decode that enters one costs much, not inf
        barrier = pot.contact.extended(cfg["barrier_extend_below"], cfg["barrier_d_hat"], cfg["barrier_kappa"])
        pot = dataclasses.replace(pot, contact=barrier)
    if compiled and device.type == "cpu":
        pot = with_compiled_elastic(pot)
    return ae_f, pot, Triplets.of(build_triplets(ae_f, coords, sequences, origin=bool(cfg["origin_input"])))


def _new_integrator(data: Triplets, cfg: dict, seed: int, device: torch.device, features: TrainingFeatures) -> LatentIntegrator:
    """An untrained integrator of settings ``cfg`` (weights seeded by ``seed``) that takes the
    features' inputs, normalised by the statistics of the triplets ``data`` with those inputs
    (:meth:`~latentsim.latent.features.TrainingFeatures.normalisation_rows`), on ``device``."""
    r, k = data.z.shape[1], data.p.shape[1] + features.extra_inputs
    fork = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=fork):
        torch.manual_seed(seed)
        integ = LatentIntegrator(r, k, cfg["widths"], residual=bool(cfg["residual"]), origin=bool(cfg["origin_input"]))
    stats = {key: getattr(data, key).cpu() for key in ("z", "z_prev", "z_prev2", "p", "p_prev", "p_prev2")}
    integ.fit_normalization(*features.normalisation_rows(stats, seed).values())
    return integ.to(device)


def _set_learning_rate(opt, cfg: dict, epoch: int, epochs: int) -> None:
    """With ``lr_final`` set, the cosine decay from ``lr`` to it: a function of the epoch alone (a
    resumed run gets the same rates); else the constant ``lr`` the optimiser holds."""
    if cfg["lr_final"] is not None:
        lr0, lr1 = float(cfg["lr"]), float(cfg["lr_final"])
        for group in opt.param_groups:
            group["lr"] = lr1 + 0.5 * (lr0 - lr1) * (1.0 + math.cos(math.pi * epoch / epochs))


def _integrator_epoch(run: _Training, data: Triplets, epoch: int, n_ground_truth: int | None = None):
    """One epoch of Adam over the triplets ``data`` in minibatches; the mean weighted loss, the
    mean latent MSE on the clean samples (against the training sequences' latents, which for a
    conditioned training are those of another condition), and the largest distance
    |z_pred - centre| of a clean sample's prediction from a ground-truth input (the first
    ``n_ground_truth`` rows; all when None).  The first minibatch of a training sets
    ``run.health``'s start and scale."""
    integ, cfg = run.integ, run.cfg
    integ.train()
    tot, mse, cnt, count, distance = 0.0, 0.0, 0, 0, 0.0
    for b, idx in enumerate(minibatches(len(data), int(cfg["batch_size"]), run.gen)):
        idx = idx.to(data.z.device)
        batch = run.features.batch(data.rows(idx), run.gen)
        loss, info = integrator_loss(
            integ, run.ae, run.coords, run.pot, batch,
            mode=cfg["mode"], noise_scale=float(cfg["noise_scale"]), balancing=bool(cfg["balancing"]),
            use_penalty=cfg["use_penalty"], balancing_eps=float(cfg["balancing_eps"]), generator=run.gen,
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
            run.health.first_batch(value, weighted)
        opt = run.opt
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
        mse += float(((info["prediction"][:nb] - batch.z) ** 2).mean()) * nb
        clean = info["prediction"][:nb] if n_ground_truth is None else info["prediction"][:nb][idx < n_ground_truth]
        if clean.shape[0]:
            distance = max(distance, float((clean - run.centre).norm(dim=-1).max()))
        cnt += nb
    return tot / count, mse / cnt, distance


def _resume(path, fingerprint: str, epochs: int, run: _Training, history: dict) -> tuple[int, float]:
    """Load the checkpoint at ``path`` into the training's integrator, optimiser, generator and
    health rule and into ``history`` when it belongs to this training (same fingerprint, no more than ``epochs`` done); the
    epoch to start from and the training time it records (0, 0.0 when there is none or it belongs
    to another training)."""
    if not os.path.exists(path):
        return 0, 0.0
    state = load_checked(path)
    if state.get("fingerprint") != fingerprint or int(state["epoch"]) > epochs:
        log.warning("checkpoint %s belongs to another training (settings, seed, architecture, data or a longer run): starting over", path)
        return 0, 0.0
    integ = run.integ
    integ.load_state_dict(state["model"])
    run.opt.load_state_dict(state["optimizer"])
    run.gen.set_state(state["generator"])
    history["loss"] = list(state["history"]["loss"])
    history["latent_mse"] = list(state["history"]["latent_mse"])
    history["latent_distance"] = list(state["history"]["latent_distance"])
    run.health.load(state["history"])
    history["start_epoch"] = int(state["epoch"])
    if state.get("own") is not None:
        history["own"] = Triplets(**{k: v.to(integ.in_mean.device) for k, v in state["own"].items()})
        history["own_triplets"] = list(state.get("own_triplets", []))
    log.info("resuming %s at epoch %d (%.1f s of training so far)", path, history["start_epoch"], float(state["train_seconds"]))
    return history["start_epoch"], float(state["train_seconds"])


def _save_checkpoint(path, fingerprint: str, seed: int, epoch_done: int, run: _Training, history: dict, seconds: float, own: Triplets | None = None) -> None:
    """Write the state after ``epoch_done`` epochs, the training time so far ``seconds`` and the
    rolled-out triplets ``own`` in use, atomically (the last good one stays on disk until the new
    one is complete)."""
    atomic_save(
        {
            "epoch": epoch_done,
            "fingerprint": fingerprint,
            "seed": seed,
            "hparams": run.integ.hparams,
            "model": run.integ.state_dict(),
            "optimizer": run.opt.state_dict(),
            "generator": run.gen.get_state(),
            "history": {k: history[k] for k in ("loss", "latent_mse", "latent_distance", "loss_start", "loss_scale")},
            "train_seconds": float(seconds),
            "own": None if own is None else {k: v.cpu() for k, v in own.fields().items()},
            "own_triplets": list(history.get("own_triplets", [])),
        },
        path,
    )

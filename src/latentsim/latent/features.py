"""The latent integrator's training features beyond the paper's loop, as pieces that the one loop of
:func:`~latentsim.latent.training.fit_integrator` consumes (:class:`TrainingFeatures`):

- the conditioning (:mod:`latentsim.latent.conditioning`): each minibatch's samples at conditions
  drawn from a box (:func:`at_sampled_conditions`);
- own rollouts: triplets whose inputs are the integrator's own latents
  (:func:`own_rollout_triplets`), at conditions of the box for a conditioned integrator
  (:func:`own_rollout_triplets_at_conditions`) and at other speeds of the programs
  (:func:`own_rollout_triplets_at_speeds`), each sequence's stopped at its first state that
  decodes deep inside a collider or into the surface itself (:class:`ClearStates`);
- the origin input (each p_t ends with the frame's mean prescribed position,
  :func:`~latentsim.latent.integrator.boundary_inputs`), which the ground truth's triplets and the
  own rollouts at speeds take;
- the balancing weights of a training whose inputs never change, computed once.

Which features go together is checked in one place, :func:`latentsim.config.check_training_features`
(also the config's check); :func:`training_features` adds what depends on the data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch

from latentsim.config import check_training_features
from latentsim.latent.autoencoder import decode_latents
from latentsim.latent.batch import Batch, Triplets
from latentsim.latent.conditioning import CONDITION_DIM, AtCondition, Conditioning, with_condition
from latentsim.latent.coordinates import RelativeCoordinates
from latentsim.latent.data import triplet_rows
from latentsim.latent.integrator import LatentIntegrator, boundary_inputs
from latentsim.latent.loss import fixed_balancing_weights
from latentsim.report.metrics import bbox_diagonal
from latentsim.scene import dirichlet_step, dirichlet_trajectory


OWN_ROLLOUT_DEPTH = 0.05
"""How deep into a collider (or into the surface itself) an own rollout's state may go, as a fraction of the
diagonal of the training states' bounding box (:class:`ClearStates`).  Measured at the first own rollout
(epoch 20) of seed 0's integrator, unstopped: the deepest state 0.4-4.7% of that diagonal on ``bunny_drop``,
``hair_head``, ``cloth_drape`` and ``cloth_sphere``; on ``cloth_fold`` half its states deeper than 6.6%, down to 35%,
and its seed 2 diverged in training from them."""


@dataclass(frozen=True)
class ClearStates:
    """Which latents decode to states the scene's potential holds: no point of the surface more than
    ``depth`` inside a collider or (with self-contact) into the rest of the surface, by the contact's
    own measure (:meth:`~latentsim.physics.contact.ContactBarrier.clearance` > -``depth``, the
    evaluation's and the frame check's).  Called with latents z (N, r) and their frames' Dirichlet
    positions xD (N, m, 3); returns a bool tensor (N,).

    An own rollout stops at its first state that is not clear (:func:`own_rollout_triplets`): the
    training's barrier is extended below the surface (``barrier_extend_below``) so that a decode
    which enters a collider costs much rather than inf, and the integrator learns from the states a
    little inside to step out of them; steps from states deep inside have energies and gradients
    that swamp the data's.
    """

    ae: torch.nn.Module
    coords: RelativeCoordinates
    contact: object
    depth: float = 0.0

    @classmethod
    def of(cls, ae: torch.nn.Module, coords: RelativeCoordinates, contact, sequences: Sequence[dict] = ()) -> "ClearStates | None":
        """The check for a scene whose potential has ``contact`` (a ContactBarrier, or None: nothing to check, None), its
        depth :data:`OWN_ROLLOUT_DEPTH` of the diagonal of the bounding box of the ``sequences``' positions (none: 0)."""
        if contact is None:
            return None
        pts = [np.asarray(s["positions"], dtype=np.float64).reshape(-1, 3) for s in sequences]
        return cls(ae, coords, contact, OWN_ROLLOUT_DEPTH * bbox_diagonal(np.concatenate(pts) if pts else np.zeros((1, 3))))

    @torch.no_grad()
    def __call__(self, z: torch.Tensor, xD: torch.Tensor) -> torch.Tensor:
        x = decode_latents(self.ae, self.coords, z, xD).cpu()
        d = self.contact.clearance(x, xD.detach().to("cpu", torch.float64))
        return d > -self.depth  # a NaN decode is not clear either


def clear_prefix(z_prev: torch.Tensor, xD_prev: torch.Tensor, clear: Callable | None) -> int:
    """How many leading rows of one rolled-out sequence to keep: those before the first whose input
    latent ``z_prev`` (N, r), at its frame's Dirichlet positions ``xD_prev`` (N, m, 3), is not
    ``clear`` (:class:`ClearStates`; None keeps all).  The rows after it start from it or from its
    successors, so they go too."""
    if clear is None or not len(z_prev):
        return len(z_prev)
    bad = torch.nonzero(~clear(z_prev, xD_prev)).flatten()
    return int(bad[0]) if len(bad) else len(z_prev)


@dataclass(frozen=True)
class OwnRollouts:
    """The own-rollouts piece: when they are due and how each training sequence is rolled out.

    Attributes
    ----------
    every, start : a rollout every ``every`` epochs from epoch ``start`` on.
    rows_per_sequence : the triplets of each training sequence (:func:`~latentsim.latent.data.triplet_rows`).
    conditioning : None, or the box a conditioned training rolls each sequence out at a condition of.
    programs, speeds : None, or the programs to roll out once more at a speed drawn from ``speeds``
        (:func:`speed_programs`).
    dt : the time step of the programs at other speeds; origin, coords : as in the training.
    """

    every: int
    start: int
    rows_per_sequence: list[int]
    conditioning: Conditioning | None = None
    programs: list | None = None
    speeds: Sequence[float] | None = None
    dt: float = 0.0
    origin: bool = False
    coords: RelativeCoordinates | None = None

    def due(self, epoch: int) -> bool:
        """Whether the 0-based ``epoch`` starts with a rollout."""
        return epoch >= self.start and (epoch - self.start) % self.every == 0

    def __call__(self, integ: LatentIntegrator, data: Triplets, centre: torch.Tensor, max_distance: float, gen: torch.Generator,
                 clear: Callable | None = None) -> Triplets:  # fmt: skip
        """The rolled-out triplets of ``integ`` from the ground truth's ``data``, each sequence stopped at its first
        state that is not ``clear`` (:class:`ClearStates`, or None)."""
        if self.conditioning is not None:
            return own_rollout_triplets_at_conditions(integ, data, self.rows_per_sequence, centre, max_distance, self.conditioning, gen, clear)
        own = own_rollout_triplets(integ, data, self.rows_per_sequence, centre, max_distance, clear)
        if self.programs is None:
            return own
        return own.cat(own_rollout_triplets_at_speeds(integ, data, self.rows_per_sequence, centre, max_distance, self.programs, self.speeds, gen,
                                                      self.dt, self.origin, self.coords, clear))  # fmt: skip


@dataclass(frozen=True)
class TrainingFeatures:
    """The pieces of one training (:func:`training_features`).

    Attributes
    ----------
    conditioning : None, or the box each minibatch's samples draw their conditions from.
    own : None, or the own-rollouts piece.
    fixed_balance : whether the balancing weights are computed once (a supervised training without
        noise or conditioning, whose inputs never change; :func:`~latentsim.latent.loss.fixed_balancing_weights`).
    balancing_eps : their floor on the speed.
    """

    conditioning: Conditioning | None = None
    own: OwnRollouts | None = None
    fixed_balance: bool = False
    balancing_eps: float = 1e-2

    @property
    def extra_inputs(self) -> int:
        """The entries the pieces append to each boundary-condition vector: a conditioned integrator's normalised condition."""
        return CONDITION_DIM if self.conditioning is not None and self.conditioning.conditioned else 0

    def normalisation_rows(self, stats: dict[str, torch.Tensor], seed: int) -> dict[str, torch.Tensor]:
        """The rows ``stats`` (``z``, ``z_prev``, ``z_prev2``, ``p``, ``p_prev``, ``p_prev2``) the integrator's
        normalisation is fitted on, with the inputs the pieces append: a conditioned integrator's
        conditions, one draw from its box per row by a generator seeded by ``seed``."""
        if not self.extra_inputs:
            return stats
        c = self.conditioning.normalise(*self.conditioning.sample(stats["z"].shape[0], torch.Generator().manual_seed(seed)))
        return {key: with_condition(val, c) if key in ("p", "p_prev", "p_prev2") else val for key, val in stats.items()}

    def prepared(self, data: Triplets, ae, coords: RelativeCoordinates, dt: float) -> Triplets:
        """The ground truth's triplets with what the pieces compute once: their balancing weights."""
        if not self.fixed_balance:
            return data
        # inputs without noise that never change: Eq. 6's weights once, not two decodes a sample every minibatch
        return data.replace(balance=fixed_balancing_weights(ae, coords, data, dt, self.balancing_eps))

    def rollouts(self, epoch: int, integ: LatentIntegrator, data: Triplets, centre: torch.Tensor, max_distance: float, gen: torch.Generator,
                 clear: Callable | None = None) -> Triplets | None:  # fmt: skip
        """The rolled-out triplets that join ``data`` from this epoch on (each sequence stopped at its first state that
        is not ``clear``, :class:`ClearStates`); None where none are due."""
        return self.own(integ, data, centre, max_distance, gen, clear) if self.own is not None and self.own.due(epoch) else None

    def batch(self, rows: Triplets, gen: torch.Generator) -> Batch:
        """The minibatch of ``rows`` as the loss takes it (each sample at a drawn condition, for a conditioned training)."""
        return Batch.of(rows) if self.conditioning is None else at_sampled_conditions(rows, self.conditioning, gen)


def training_features(cfg: dict, sequences: Sequence[dict], coords: RelativeCoordinates, dt: float, conditioning: Conditioning | None, label: str = "") -> TrainingFeatures:
    """The pieces of a training of settings ``cfg`` (the schema's ``integrator``, complete) on
    ``sequences`` at time step ``dt``, over ``conditioning``'s box (or None).

    Raises ValueError (:class:`~latentsim.config.ConfigError`), naming ``label`` and the setting,
    where features do not go together (:func:`~latentsim.config.check_training_features`), where
    ``origin_input`` meets a free body, and where the programs cannot be scaled (:func:`speed_programs`).
    """
    check_training_features(cfg, lambda k: f"{label}: {k}" if label else k, conditioned=conditioning is not None, rigid_frame=bool(coords.rigid))
    if cfg["origin_input"] and any(np.shape(s["dirichlet_positions"])[-2] == 0 for s in sequences):
        raise ValueError(f"{label or 'integrator'}: origin_input needs prescribed vertices (a free body's latent is already where it is in the world)")
    own = None
    if int(cfg["own_rollouts_every"]) > 0:
        own = OwnRollouts(int(cfg["own_rollouts_every"]), int(cfg["own_rollouts_start"]), triplet_rows(sequences), conditioning,
                          speed_programs(sequences, cfg["own_rollouts_speeds"], label), cfg["own_rollouts_speeds"], float(dt),
                          bool(cfg["origin_input"]), coords)  # fmt: skip
    fixed = cfg["mode"] == "supervised" and not float(cfg["noise_scale"]) and bool(cfg["balancing"]) and conditioning is None
    return TrainingFeatures(conditioning, own, fixed, float(cfg["balancing_eps"]))


def at_sampled_conditions(batch: Triplets, conditioning: Conditioning, gen: torch.Generator) -> Batch:
    """The minibatch with a condition drawn for each sample (:class:`Conditioning`; a row with a
    finite ``condition`` (h, E), rolled out at it, keeps it): its time step
    ``dt``, elastic factor ``stiffness`` and weight ``scale`` (:meth:`Conditioning.weight`), the frame-t Dirichlet
    targets that the boundary-condition program gives at its time step, and (for a conditioned
    integrator) the normalised condition appended to each boundary-condition vector."""
    h, E = conditioning.sample(len(batch), gen)
    fixed = batch.condition
    if fixed is not None:  # a rolled-out row keeps the condition it was rolled out at
        keep = torch.isfinite(fixed[:, 0]).cpu()
        h = torch.where(keep, fixed[:, 0].cpu().to(h.dtype), h)
        E = torch.where(keep, fixed[:, 1].cpu().to(E.dtype), E)
    dev = batch.xD.device
    dt = h.to(dev)
    out = Batch.of(batch).replace(condition=None, dt=dt, stiffness=(E / conditioning.base_modulus).to(dev), scale=conditioning.weight(h).to(dev),
                                  xD=dirichlet_step(batch.xD_prev, batch.p, dt))  # fmt: skip
    if conditioning.conditioned:
        c = conditioning.normalise(h, E).to(dev)
        out = out.replace(p=with_condition(batch.p, c), p_prev=with_condition(batch.p_prev, c), p_prev2=with_condition(batch.p_prev2, c))
    return out


@torch.no_grad()
def own_rollout_triplets(integ: LatentIntegrator, data, rows_per_sequence: Sequence[int], centre: torch.Tensor, max_distance: float,
                         clear: Callable | None = None) -> Triplets:  # fmt: skip
    """Triplets whose inputs are the integrator's own latents: each training sequence of ``data``
    (:class:`~latentsim.latent.batch.Triplets`, or a dict of its fields, of
    :func:`~latentsim.latent.data.build_triplets`: ``rows_per_sequence[i]`` rows of sequence i,
    in order) rolled out from its first two ground-truth latents under its boundary conditions,
    until it ends or a latent lies farther than ``max_distance`` from ``centre``, and (with
    ``clear``, :class:`ClearStates`) only up to the row before the first whose input latent is not
    clear at its frame's Dirichlet positions (:func:`clear_prefix`).  Each row keeps
    the frame's boundary conditions, Dirichlet targets and ground-truth latent ``z``; its
    ``z_prev`` and ``z_prev2`` are the rolled-out ones (a sequence's first row keeps its ground
    truth: it is the first step).  The training mode of ``integ`` is restored."""
    data = Triplets.of(data)
    if sum(rows_per_sequence) != len(data):
        raise ValueError(f"rows_per_sequence sums to {sum(rows_per_sequence)}, the triplets have {len(data)} rows")
    was_training = integ.training
    integ.eval()
    ends = np.cumsum(rows_per_sequence).tolist()
    rows, z_prev, z_prev2 = [], [], []
    for a, b in zip([0] + ends[:-1], ends):
        z2, z1 = data.z_prev2[a], data.z_prev[a]
        seq, seq_prev, seq_prev2 = [], [], []
        for i in range(a, b):
            seq.append(i)
            seq_prev.append(z1)
            seq_prev2.append(z2)
            z = integ(z1[None], z2[None], data.p[i : i + 1], data.p_prev[i : i + 1], data.p_prev2[i : i + 1])[0].to(z1.dtype)
            if not torch.isfinite(z).all() or float((z - centre).norm()) > max_distance:
                break
            z2, z1 = z1, z
        n = clear_prefix(torch.stack(seq_prev), data.xD_prev[seq], clear)
        rows += seq[:n]
        z_prev += seq_prev[:n]
        z_prev2 += seq_prev2[:n]
    if was_training:
        integ.train()
    out = data.rows(torch.as_tensor(rows, dtype=torch.long, device=data.z.device))
    return out.replace(z_prev=torch.stack(z_prev), z_prev2=torch.stack(z_prev2)) if rows else out


@torch.no_grad()
def own_rollout_triplets_at_conditions(
    integ: LatentIntegrator, data, rows_per_sequence: Sequence[int], centre: torch.Tensor, max_distance: float, conditioning: Conditioning, gen: torch.Generator,
    clear: Callable | None = None,
) -> Triplets:  # fmt: skip
    """:func:`own_rollout_triplets` of a conditioned integrator: each training sequence rolled out at
    one condition (h, E) drawn from ``conditioning``'s box by ``gen``, its boundary-condition program
    (the frames' p_t) stepped at h from the sequence's first Dirichlet positions.  Each row holds
    the Dirichlet targets of its frames at h and its ``condition`` (h, E) (float64, (N, 2)), at
    which its loss is to be taken (:func:`at_sampled_conditions`); with ``clear``, each sequence stopped as
    :func:`own_rollout_triplets` stops it, at those Dirichlet targets."""
    data = Triplets.of(data)
    ends = np.cumsum(rows_per_sequence).tolist()
    h, E = conditioning.sample(len(ends), gen)
    parts = []
    for a, b, hi, Ei in zip([0] + ends[:-1], ends, h.tolist(), E.tolist()):
        sub = data.rows(slice(a, b))
        at = AtCondition(integ, conditioning.normalise(hi, Ei)).to(data.z.device) if conditioning.conditioned else integ
        own = own_rollout_triplets(at, sub, [b - a], centre, max_distance)
        n = len(own)
        p = torch.cat([sub.p_prev2[:1], sub.p_prev[:1], sub.p[:n]])  # frames 0 .. n + 1
        xD = [sub.xD_prev2[0]]
        for t in range(1, n + 2):
            xD.append(dirichlet_step(xD[-1][None], p[t : t + 1], hi)[0])
        xD = torch.stack(xD)
        condition = torch.tensor([hi, Ei], dtype=torch.float64, device=xD.device).expand(n, 2).clone()
        own = own.replace(xD_prev2=xD[:n], xD_prev=xD[1 : n + 1], xD=xD[2:], condition=condition)
        parts.append(own.rows(slice(0, clear_prefix(own.z_prev, own.xD_prev, clear))))
    return parts[0].cat(*parts[1:])


def speed_programs(sequences: Sequence[dict], speeds, label: str = "") -> list | None:
    """What ``own_rollouts_speeds`` (``speeds``, [lo, hi] or None) scales: for each training
    sequence that gives triplets (in :func:`~latentsim.latent.data.triplet_rows`' order), its
    boundary-condition program (T, 6) (float64; None where the program is still, a free body: no
    speed to scale) and its first frame's prescribed positions (m, 3); None where ``speeds`` is
    None.  Raises ValueError, naming the key, where the range or the programs cannot be scaled
    (which settings it goes with is :func:`~latentsim.config.check_training_features`' check)."""
    if speeds is None:
        return None
    what = f"{label or 'integrator'}: integrator.own_rollouts_speeds"
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
    integ: LatentIntegrator, data, rows_per_sequence: Sequence[int], centre: torch.Tensor, max_distance: float, programs: Sequence, speeds,
    gen: torch.Generator, dt: float, origin: bool, coords: RelativeCoordinates | None = None, clear: Callable | None = None,
) -> Triplets:  # fmt: skip
    """:func:`own_rollout_triplets` under faster or slower programs: each training sequence whose
    program moves (``programs``, :func:`speed_programs`) rolled out from its first two ground-truth
    latents under its program with every velocity and angular velocity scaled by a factor f drawn by
    ``gen`` log-uniformly from ``speeds`` = [lo, hi], its prescribed positions stepped from its first
    frame's by the scaled program at the time step ``dt`` (:func:`~latentsim.scene.dirichlet_trajectory`),
    and the integrator's inputs made of them (:func:`~latentsim.latent.integrator.boundary_inputs`,
    ``origin`` and ``coords`` as in the training).  Each row holds the frame's Dirichlet targets
    under the scaled program (the self-supervised loss needs nothing else there); its ``z`` is the
    recorded frame's, as no ground truth exists at other speeds.  Also holds ``speed`` (N,), each
    row's factor.  ``clear``: as in :func:`own_rollout_triplets`, at the scaled program's targets."""
    data = Triplets.of(data)
    lo, hi = (math.log(float(v)) for v in speeds)
    ends = np.cumsum(rows_per_sequence).tolist()
    factors = torch.exp(lo + (hi - lo) * torch.rand(len(ends), generator=gen, dtype=torch.float64)).tolist()
    parts = []
    for a, b, (bc, xD0), f in zip([0] + ends[:-1], ends, programs, factors):
        if bc is None:
            continue
        sub = data.rows(slice(a, b))
        xD = dirichlet_trajectory(xD0, f * bc, dt)
        p = torch.as_tensor(boundary_inputs(f * bc, xD, origin, coords)).to(sub.p)
        xD = torch.as_tensor(xD).to(sub.xD)
        sub = sub.replace(p=p[2:], p_prev=p[1:-1], p_prev2=p[:-2], xD=xD[2:], xD_prev=xD[1:-1], xD_prev2=xD[:-2])
        own = own_rollout_triplets(integ, sub, [b - a], centre, max_distance, clear)
        parts.append(own.replace(speed=torch.full((len(own),), f, dtype=torch.float64, device=own.z.device)))
    return parts[0].cat(*parts[1:])

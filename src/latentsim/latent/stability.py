"""Stress conditions for stability tests: where do learned integrators fail?

The boundary-condition program of a test sequence, ``p_t = [v_t, w_t]``
(:func:`latentsim.scene.bc_parameters`), is transformed into harder
programs that no method saw during training:

- ``long_x10``: the test program repeated until the rollout is 10 times the
  longest training sequence;
- ``speed_x{f}``: every velocity scaled by ``f`` (0.1x to 5x of the training
  range);
- ``sudden_stop`` / ``sudden_reversal``: the program zeroed / negated from a
  third of the sequence on;
- ``perturbed_start``: the test program from a perturbed initial state (the
  caller applies ``perturbation``, e.g. noise on the initial latents).

Every condition starts from the test sequence's first two frames (the
ground-truth latents z_0, z_1; perturbed for ``perturbed_start``).  A
condition needs no ground truth beyond them: what is measured is how long a method
survives (no NaN, bounded extent) and how well it keeps the boundary
conditions, which are known exactly from the program.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from latentsim.config import with_defaults
from latentsim.latent.autoencoder import decode_latents, encode_positions
from latentsim.latent.integrator import boundary_inputs
from latentsim.latent.rollout import past_extent
from latentsim.report.metrics import bbox_diagonal, dirichlet_error
from latentsim.scene import dirichlet_trajectory


@dataclass
class Condition:
    """One stress condition.

    Attributes
    ----------
    name : e.g. ``speed_x5``.
    bc : (T, k) boundary-condition parameters p_t.
    dirichlet_positions : (T, m, 3) prescribed positions of the Dirichlet vertices.
    perturbation : relative size of the initial-state perturbation (0: none).
    """

    name: str
    bc: np.ndarray
    dirichlet_positions: np.ndarray
    perturbation: float = 0.0


def _label(f: float) -> str:
    return f"speed_x{f:g}".replace(".", "p")


def stress_programs(bc: np.ndarray, train_frames: int, factors, long_factor: int) -> dict[str, np.ndarray]:
    """Transformed BC programs of one test sequence.

    Parameters
    ----------
    bc : (T, k) the test sequence's p_t (p_0 = 0: scenes start at rest).
    train_frames : length of the longest training sequence.
    factors : speed factors.
    long_factor : the long rollout lasts ``long_factor * train_frames`` frames.

    Returns
    -------
    {name: (T', k)} with p_0 = 0 in every program.  A program without motion (a free body, which has
    no prescribed set, or a scene held still) has no speed to scale, stop or reverse: those conditions
    would be the test sequence itself and are left out, so only ``long_x{f}`` and ``perturbed_start``
    remain.
    """
    bc = np.asarray(bc, dtype=float)
    if bc.ndim != 2 or len(bc) < 3:
        raise ValueError(f"bc must be (T >= 3, k), got shape {bc.shape}")
    T = len(bc)
    out: dict[str, np.ndarray] = {}
    n_long = max(int(long_factor * train_frames), T)
    motion = bc[1:]
    reps = int(np.ceil((n_long - 1) / len(motion)))
    out[f"long_x{long_factor}"] = np.concatenate([bc[:1], np.tile(motion, (reps, 1))[: n_long - 1]])
    if not bc.any():
        out["perturbed_start"] = bc.copy()
        return out
    for f in factors:
        out[_label(f)] = bc * f
    cut = max(T // 3, 2)
    stop = bc.copy()
    stop[cut:] = 0.0
    out["sudden_stop"] = stop
    rev = bc.copy()
    rev[cut:] *= -1.0
    out["sudden_reversal"] = rev
    out["perturbed_start"] = bc.copy()
    return out


def stress_conditions(bc, rest_dirichlet, dt: float, train_frames: int, factors, long_factor: int,
                      perturbation: float) -> list[Condition]:  # fmt: skip
    """:func:`stress_programs` with the Dirichlet trajectories they prescribe.

    rest_dirichlet : (m, 3) rest positions of the Dirichlet vertices; dt : time step [s].
    perturbation : relative size of the perturbation of ``perturbed_start``.
    """
    out = []
    for name, p in stress_programs(bc, train_frames, factors, long_factor).items():
        xD = dirichlet_trajectory(rest_dirichlet, p, dt)
        out.append(Condition(name, p, xD, perturbation if name == "perturbed_start" else 0.0))
    return out


def survive_latent(integrator, ae, coords, z0, z1, condition: Condition, dirichlet, rest_diag: float,
                   max_extent: float, latent_std=None, seed: int = 0, chunk: int = 256, contact=None, projection=None) -> dict:  # fmt: skip
    """Roll a latent integrator out under one condition; how long does it survive?

    The latents are integrated autoregressively from ``z0, z1`` (perturbed by
    ``condition.perturbation * latent_std`` Gaussian noise for perturbed
    starts), then decoded in chunks (the long conditions would not fit in
    memory at once).  A frame fails when its latent or decoded positions are
    non-finite or its bounding-box diagonal exceeds ``max_extent * rest_diag``.

    Returns
    -------
    dict with ``frames`` (T), ``survived`` (frames before the first failure,
    T when none), ``dirichlet_error_end`` (mean Dirichlet error / rest_diag
    at the last surviving frame) and ``dirichlet_error`` ((survived,) per frame); with ``contact``
    (a :class:`~latentsim.physics.contact.ContactBarrier`, the scene's colliders) also
    ``max_penetration``, the deepest entry into a collider of any surviving frame / rest_diag.  With
    ``projection`` (a :class:`~latentsim.latent.projection.ContactProjection`, the rollout's
    ``contact_projection``) the surviving frames near a collider are projected out of it as the test
    rollouts' are, ``max_penetration`` is the projected frames' and ``max_penetration_own`` the
    network's own; ``projected_frames`` counts them.  Survival is the network's unless the projection
    feeds back (its ``feedback``): then each projected latent is the next step's input, the frames are
    the projected state's, and ``max_penetration_own`` is the deepest of the network's one-step
    predictions before projection.
    """
    bc = torch.as_tensor(boundary_inputs(np.asarray(condition.bc), condition.dirichlet_positions, getattr(integrator, "origin", False), coords), dtype=torch.float32)
    T = len(bc)
    z0 = torch.as_tensor(z0, dtype=torch.float32).clone()
    z1 = torch.as_tensor(z1, dtype=torch.float32).clone()
    if condition.perturbation > 0:
        g = torch.Generator().manual_seed(seed)
        std = torch.ones_like(z0) if latent_std is None else torch.as_tensor(latent_std, dtype=torch.float32)
        z0 += condition.perturbation * std * torch.randn(z0.shape, generator=g)
        z1 += condition.perturbation * std * torch.randn(z1.shape, generator=g)
    Z = torch.full((T, z0.shape[-1]), float("nan"))
    Z[0], Z[1] = z0, z1
    last = T
    fed = projection.step(condition.dirichlet_positions) if projection is not None and projection.feedback else None
    if fed is not None:  # the starting state too
        Z[0], Z[1] = fed(0, Z[0]), fed(1, Z[1])
    xD_all = torch.as_tensor(condition.dirichlet_positions, dtype=torch.float64)
    with torch.inference_mode():
        for t in range(2, T):
            Z[t] = integrator(Z[t - 1 : t], Z[t - 2 : t - 1], bc[t : t + 1], bc[t - 1 : t], bc[t - 2 : t - 1])[0]
            if not torch.isfinite(Z[t]).all():
                last = t
                break
            if fed is not None:
                with torch.inference_mode(False):
                    Z[t] = fed(t, Z[t])
                if past_extent(ae, coords, Z[t], xD_all[t], max_extent * rest_diag):  # its first failure: none corrected past it
                    last = t + 1
                    break
        errors, depth, own_depth, projected = [], 0.0, 0.0, 0
        survived = last
        for s in range(0, last, chunk):
            e = min(s + chunk, last)
            x = decode_latents(ae, coords, Z[s:e], xD_all[s:e]).cpu().numpy()
            ext = np.linalg.norm(x.max(-2) - x.min(-2), axis=-1)
            bad = ~np.isfinite(x).all(axis=(-1, -2)) | (ext > max_extent * rest_diag)
            x = np.where(np.isfinite(x), x, 0.0)
            err = dirichlet_error(x, dirichlet, condition.dirichlet_positions[s:e], rest_diag)
            k = int(np.argmax(bad)) if bad.any() else e - s
            if contact is not None and k:
                deepest = _deepest(contact, x[:k], xD_all[s : s + k])  # of the frames as decoded
                own_depth = max(own_depth, deepest)
                if fed is not None:  # the frames are already the projected state's
                    depth = max(depth, deepest)
                    own_depth = max(own_depth, float(fed.own_depth[s : s + k].max()))
                    projected += int(fed.projected[s : s + k].sum())
                elif projection is not None:
                    with torch.inference_mode(False):  # the projection differentiates the decoder
                        done = projection.frames(Z[s : s + k].numpy(), x[:k], condition.dirichlet_positions[s : s + k])
                    projected += int(done["projected"].sum())
                    depth = max(depth, _deepest(contact, done["positions"], xD_all[s : s + k]))
                else:
                    depth = own_depth
            if bad.any():
                errors.append(err[:k])
                survived = s + k
                break
            errors.append(err)
    err = np.concatenate(errors) if errors else np.zeros(0)
    out = {"frames": T, "survived": int(survived), "dirichlet_error": err,
           "dirichlet_error_end": float(err[-1]) if len(err) else float("nan")}  # fmt: skip
    if contact is not None:
        out["max_penetration"] = depth / rest_diag
        if projection is not None:
            out["max_penetration_own"] = own_depth / rest_diag
            out["projected_frames"] = projected
    return out


def _deepest(contact, x, xD) -> float:
    """The deepest entry of frames ``x`` (T, n, 3) into the colliders posed by ``xD`` (T, m, 3) [m]; 0 when none enters."""
    d = contact.clearance(torch.as_tensor(x, dtype=torch.float64), xD).numpy()
    return float(np.maximum(-d, 0.0).max())


def stress_test(integrator, ae, coords, sequence: dict, rest_positions, dirichlet, dt: float, train_frames: int,
                settings: dict, max_extent: float, contact=None, projection=None):  # fmt: skip
    """Every stress condition of ``settings`` (a scene's ``rollout.stability``; keys absent take the
    config schema's defaults) on one test sequence.

    One implementation for the rollout stage's stability map and the sizing
    sweep's check.  The conditions start from the sequence's first two frames,
    encoded; the perturbation's scale is the std of the sequence's latents.

    Parameters
    ----------
    sequence : a test sequence (``positions``, ``dirichlet_positions``, ``bc``).
    rest_positions : (n, 3); dirichlet : (m,) indices; dt : time step [s].
    train_frames : length of the longest training sequence.
    contact : the scene's contact barrier (its colliders), or None: each result then also holds the
        deepest entry into one (:func:`survive_latent`).
    projection : None, or the rollout's contact projection: the conditions' frames near a collider are
        projected as the test rollouts' are (:func:`survive_latent`).

    Yields
    ------
    (condition, result of :func:`survive_latent`), one condition at a time.
    """
    st = with_defaults("stability", settings, "stress_test")
    x = torch.as_tensor(sequence["positions"])
    xD = torch.as_tensor(sequence["dirichlet_positions"])
    z = encode_positions(ae, coords, x, xD)
    rest = np.asarray(rest_positions)
    conditions = stress_conditions(
        sequence["bc"], rest[dirichlet], float(dt), int(train_frames),
        factors=st["speed_factors"], long_factor=int(st["long_factor"]), perturbation=float(st["perturbation"]),
    )  # fmt: skip
    for c in conditions:
        yield c, survive_latent(integrator, ae, coords, z[0], z[1], c, dirichlet, bbox_diagonal(rest), float(max_extent),
                                latent_std=z.std(0), seed=0, contact=contact, projection=projection)  # fmt: skip

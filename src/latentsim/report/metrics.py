"""Metrics of a rollout against the full-space ground truth (Li et al. 2025, Sec. 6 and Figs. 8-12).

Every length is relative to the rest shape's bounding-box diagonal ``diag``
(:func:`bbox_diagonal`), so scenes of any size compare.  Per test sequence
(:func:`rollout_metrics`), over the whole sequence:

- ``mean_error`` / ``max_error``: mean over frames of the mean vertex distance
  to the ground truth, and the largest vertex distance of any frame
  (:func:`vertex_errors`);
- ``dirichlet_error``: mean distance of the Dirichlet vertices to their
  prescribed positions;
- ``kinetic_ratio``: mean kinetic energy of the rollout over that of the
  ground truth (:func:`kinetic_energy`; 1 = no numerical damping);
- ``end_error`` / ``end_motion`` / ``end_motion_truth``: the steady state
  (last 10% of the frames, Li et al. Fig. 10): mean error there, and the RMS
  vertex displacement per frame of the rollout and of the ground truth
  (0 at rest).

Divergence (:data:`DIVERGED_ERROR`): the frames from a rollout's first diverged
frame on count as failed, with an infinite error, so a rollout that diverged at
any frame (frame 0 included) has infinite ``mean_error``, ``max_error``,
``dirichlet_error`` and ``end_error``, and NaN ``kinetic_ratio`` and
``end_motion`` (not measurable over the whole sequence); ``diverged_frame`` is
the number of frames it survived.  Its errors over the frames it survived stay
in the per-frame curves (the figure of errors over time).  A diverged method
thus never has the best error and is never on a Pareto front
(:func:`pareto_front` leaves non-finite points out).

:func:`pareto_front` marks the non-dominated methods of a speed-accuracy
comparison.  :func:`penetration` measures how deep a motion enters a scene's colliders (a rollout's, or
an autoencoder's reconstruction of the ground truth).  NumPy, and torch for the colliders' distances:
no plotting library is imported here.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["DIVERGED_ERROR", "bbox_diagonal", "kinetic_energy", "pareto_front", "penetration", "rollout_metrics", "vertex_errors"]

# the error of a failed frame (at and after a rollout's first diverged frame); a rollout with one
# failed frame has this mean and max error, so it ranks behind every rollout that survived
DIVERGED_ERROR = float("inf")


def bbox_diagonal(x: np.ndarray) -> float:
    """Length of the diagonal of the axis-aligned bounding box of the points ``x`` (n,3)."""
    return float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))


def kinetic_energy(positions: np.ndarray, masses: np.ndarray, dt: float) -> np.ndarray:
    """Kinetic energy 1/2 sum_i m_i |v_i|^2 per frame, with backward-difference velocities.

    Parameters
    ----------
    positions : (T,n,3) float, a motion.
    masses : (n,) float, lumped vertex masses.
    dt : float, time step [s].

    Returns
    -------
    (T,) float [J]; frame 0 (no previous frame) is 0 (empty for T = 0).
    """
    if len(positions) == 0:
        return np.zeros(0)
    v = np.diff(positions, axis=0) / dt
    ke = 0.5 * np.einsum("n,tn->t", masses, (v * v).sum(-1))
    return np.concatenate([[0.0], ke])


def vertex_errors(pred: np.ndarray, truth: np.ndarray, diag: float):
    """Per-frame mean and max vertex distance between two motions (T,n,3), over ``diag``; each (T,)."""
    d = np.linalg.norm(pred - truth, axis=-1) / diag
    return d.mean(axis=-1), d.max(axis=-1)


def dirichlet_error(positions: np.ndarray, dirichlet: np.ndarray, targets: np.ndarray, diag: float) -> np.ndarray:
    """Mean distance of the Dirichlet vertices from their targets / diag, per frame; NaN for a free body
    (no Dirichlet vertex).

    positions : (T, n, 3); dirichlet : (m,) indices; targets : (T, m, 3) -> (T,).
    """
    if len(dirichlet) == 0:
        return np.full(len(positions), np.nan)
    d = np.linalg.norm(positions[:, dirichlet] - targets, axis=-1)
    return d.mean(-1) / diag


def rollout_metrics(pred, truth, dirichlet_truth, dirichlet, masses, dt: float, diag: float, diverged_frame: int):
    """The metrics of one rollout of a test sequence against the ground truth (see the module docstring).

    Parameters
    ----------
    pred, truth : (T,n,3) float, rollout and ground-truth positions.
    dirichlet_truth : (T,m,3) float, the prescribed positions of the Dirichlet vertices.
    dirichlet : (m,) int, the Dirichlet vertices.
    masses : (n,) float; dt : time step [s]; diag : the rest bounding-box diagonal.
    diverged_frame : first diverged frame of the rollout (0 <= . < T), -1 when stable.

    Returns
    -------
    metrics : dict ``frames``, ``diverged_frame``, ``mean_error``, ``max_error``, ``dirichlet_error``,
        ``kinetic_ratio``, ``end_error``, ``end_motion``, ``end_motion_truth`` (in this order: a table's
        columns); the errors of a diverged rollout are :data:`DIVERGED_ERROR` (infinite), its
        ``kinetic_ratio`` and ``end_motion`` NaN.
    curves : dict of per-frame arrays over the frames before divergence (empty for a divergence at
        frame 0), ``mean_error``, ``dirichlet_error``, ``ke_truth``, ``ke_pred``, with ``dt``,
        ``frames`` and ``diverged_frame``.
    """
    T, div = len(truth), int(diverged_frame)
    if not -1 <= div < T:
        raise ValueError(f"rollout_metrics: diverged_frame {div} is outside -1 (stable) .. {T - 1} (a frame of the {T})")
    ok = slice(0, T if div < 0 else div)
    mean_e, max_e = vertex_errors(pred[ok], truth[ok], diag)
    bc_e = dirichlet_error(pred[ok], dirichlet, dirichlet_truth[ok], diag)
    ke_t, ke_p = kinetic_energy(truth[ok], masses, dt), kinetic_energy(pred[ok], masses, dt)
    # the end of the sequence (last 10% of frames; Li et al. Fig. 10's steady state): error and
    # residual motion (RMS vertex displacement per frame / diag; 0 at rest)
    tail = slice(max(1, T - max(T // 10, 2)), T)
    step_t = np.linalg.norm(np.diff(truth[tail.start - 1 : T], axis=0), axis=-1)
    if div < 0:
        step = np.linalg.norm(np.diff(pred[tail.start - 1 : T], axis=0), axis=-1)
        errors = dict(mean_error=float(mean_e.mean()), max_error=float(max_e.max()), dirichlet_error=float(bc_e.mean()),
                      kinetic_ratio=float(np.nanmean(ke_p) / max(np.nanmean(ke_t), 1e-300)), end_error=float(mean_e[tail].mean()),
                      end_motion=float(np.sqrt((step**2).mean()) / diag))  # fmt: skip
    else:  # the frames from ``div`` on failed: infinite error over the whole sequence
        errors = dict(mean_error=DIVERGED_ERROR, max_error=DIVERGED_ERROR, dirichlet_error=DIVERGED_ERROR, kinetic_ratio=np.nan,
                      end_error=DIVERGED_ERROR, end_motion=np.nan)  # fmt: skip
    metrics = dict(frames=T, diverged_frame=div, mean_error=errors["mean_error"], max_error=errors["max_error"],
                   dirichlet_error=errors["dirichlet_error"], kinetic_ratio=errors["kinetic_ratio"], end_error=errors["end_error"],
                   end_motion=errors["end_motion"], end_motion_truth=float(np.sqrt((step_t**2).mean()) / diag))  # fmt: skip
    curves = dict(mean_error=mean_e, dirichlet_error=bc_e, ke_truth=ke_t, ke_pred=ke_p, dt=dt, frames=T, diverged_frame=div)
    return metrics, curves


PENETRATION_LIMIT = 0.01
"""The deepest entry into a collider (over the rest bounding-box diagonal) a method may make and still stand on
a scene's speed-accuracy front (:func:`latentsim.report.tables.speed_accuracy_points`); the stability map
frames a stress condition deeper than it."""


def pareto_front(times, errors) -> np.ndarray:
    """Mask of the non-dominated points (lower-left front: fast and accurate).

    Point ``i`` is dominated when another point ``j`` is no slower and no less
    accurate, and strictly better in one of the two.  Identical points do not
    dominate each other (duplicates are all on the front).  Points whose time
    or error is NaN or infinite (e.g. a diverged method) are never on the front
    and dominate nothing.

    Parameters
    ----------
    times : (p,) float
        Cost per point, e.g. ms per frame.
    errors : (p,) float
        Error per point.

    Returns
    -------
    on_front : (p,) bool
    """
    t = np.asarray(times, dtype=float).ravel()
    e = np.asarray(errors, dtype=float).ravel()
    if t.shape != e.shape:
        raise ValueError(f"pareto_front: times {t.shape} and errors {e.shape} differ in length")
    ok = np.isfinite(t) & np.isfinite(e)
    tv, ev = t[ok], e[ok]
    # dominated[i] = any_j (t_j <= t_i & e_j <= e_i & (t_j < t_i | e_j < e_i))
    no_worse = (tv[None, :] <= tv[:, None]) & (ev[None, :] <= ev[:, None])
    better = (tv[None, :] < tv[:, None]) | (ev[None, :] < ev[:, None])
    dominated = (no_worse & better).any(axis=1)
    mask = np.zeros(t.shape, dtype=bool)
    mask[np.flatnonzero(ok)] = ~dominated
    return mask


def penetration(contact, positions, diag: float, diverged_frame: int, dirichlet_positions=None) -> dict:
    """How far a motion's vertices (a rollout's, or a reconstruction's) enter the scene's colliders, over the
    frames before ``diverged_frame`` (-1: all): ``max_penetration`` (the deepest point of the surface, vertex, edge or triangle, in any frame / the rest bbox
    diagonal; 0 when none enters) and ``penetrating_frames`` (frames with any point of the surface inside).  ``dirichlet_positions`` (T, m, 3), the
    sequence's prescribed positions, place the colliders attached to them (needed with one)."""
    ok = positions[: len(positions) if diverged_frame < 0 else diverged_frame]
    if not len(ok):
        return {"max_penetration": float("nan"), "penetrating_frames": 0}
    targets = None if dirichlet_positions is None else np.asarray(dirichlet_positions)[: len(ok)]
    d = contact.clearance(torch.as_tensor(ok, dtype=torch.float64), targets).numpy()
    return {"max_penetration": float(np.maximum(-d, 0.0).max() / diag), "penetrating_frames": int((d < 0).sum())}

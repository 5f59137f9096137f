r"""Subspace dynamics in Neural Modes (Wang et al. 2024, Eq. 15) through ``latentsim.solve.reduced``.

Eq. 15 minimises the incremental potential over the modal coordinates,

    z_{n+1} = argmin_z 1/(2h^2) ||n(z) - 2 x_n + x_{n-1}||_M^2 + E(n(z)),

which is :class:`latentsim.solve.reduced.ReducedImplicitEuler` with the map
``x = phi(z, x*_D)`` given here (the paper solves it with L-BFGS; the reduced
solver also offers Gauss-Newton on J^T H J, the "exact reduced Hessian" the
paper lists as future work).  Our wang2024 scenes hold a Dirichlet set that
moves rigidly (hooves, base); the modes were computed with that set fixed at
rest, so the map carries the whole Neural Mode with the set's rigid motion,

    phi(z, x*_D) = R (n(z) - c_0) + c,     (R, c) the Kabsch fit of X_D -> x*_D,

which places the Dirichlet vertices exactly (n(z) leaves them at rest), so the
subspace imposes the boundary conditions (``hard_dirichlet``).  The map and
its Jacobian are evaluated by ``numpy_map.NumpyNeuralModes`` (float64 NumPy,
forward mode through the GELU MLP; no PyTorch in the step: see that module for
why and for the timings).
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from latentsim.neural_modes.network import NeuralModes
from latentsim.neural_modes.numpy_map import NumpyNeuralModes
from latentsim.labels import DYNAMICS_METHODS
from latentsim.report.metrics import bbox_diagonal
from latentsim.scene import potential_from_artefact
from latentsim.solve.cubature import box_samples, cubature_potential, fit_cubature
from latentsim.solve.reduced import ReducedSettings, reduced_rollout

log = logging.getLogger(__name__)

__all__ = ["NeuralModesSubspace", "keyframe_coordinates", "relative_errors", "smallest_rotation", "subspace_dynamics"]


def smallest_rotation(a, b) -> np.ndarray:
    """The rotation of least angle that turns the direction a onto b (3-vectors)."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    v, cos = np.cross(a, b), float(a @ b)
    sin = float(np.linalg.norm(v))
    if sin < 1e-12:
        if cos > 0:
            return np.eye(3)
        axis = np.cross(a, np.eye(3)[np.argmin(np.abs(a))])  # a half turn about an axis across a
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + K + K @ K * ((1.0 - cos) / sin**2)


class NeuralModesSubspace:
    """x = R (n(z) - c_0) + c for :class:`latentsim.solve.reduced.ReducedImplicitEuler`.

    Parameters
    ----------
    model : trained :class:`NeuralModes` (its fixed DoFs are the scene's Dirichlet set).
    dirichlet : (m,) the scene's Dirichlet vertices.
    linear_only : use the linear modes alone (y = 0): the linear-modes baseline.
    """

    def __init__(self, model: NeuralModes, dirichlet, linear_only: bool = False):
        self.net = NumpyNeuralModes(model)
        self.dim = int(model.m)
        self.n_vertices = int(model.n)
        self.dirichlet = np.asarray(dirichlet, dtype=np.int64)
        self.hard_dirichlet = len(self.dirichlet) > 0
        self.X, self.E = self.net.X, self.net.E
        self.linear_only = bool(linear_only)
        XD = self.X.reshape(-1, 3)[self.dirichlet]
        self.c0 = XD.mean(0) if len(XD) else np.zeros(3)
        self._XDc = XD - self.c0

    def _correction(self, q, jac):
        """y (3n,) and, with ``jac``, dy/dq (3n, m): the network's, or zero for the linear modes alone."""
        if self.linear_only:
            return np.zeros_like(self.X), (np.zeros((len(self.X), self.dim)) if jac else None)
        return self.net.correction(q, jac)

    def _frame(self, xD):
        """Rotation R and centre c of the best rigid fit of the rest Dirichlet set onto xD.

        A collinear set (the cloth's two corners) fixes no rotation about its own line: the
        fit's singular vectors across that line are arbitrary.  Then R is the smallest
        rotation that turns the rest line onto the current one (the identity while the set
        only translates)."""
        if not len(self.dirichlet):
            return np.eye(3), self.c0
        xD = np.asarray(xD, dtype=np.float64)
        c = xD.mean(0)
        U, S, Vt = np.linalg.svd(self._XDc.T @ (xD - c))
        if S[1] <= 1e-9 * S[0]:  # collinear (or a single vertex: S = 0, no turn at all)
            return (smallest_rotation(U[:, 0], Vt[0]) if S[0] > 0 else np.eye(3)), c
        d = np.sign(np.linalg.det(U @ Vt))
        return (U @ np.diag([1.0, 1.0, d]) @ Vt).T, c

    def map(self, q, xD) -> np.ndarray:
        q = np.asarray(q, dtype=np.float64)
        y, _ = self._correction(q, False)
        n = (self.X + self.E @ q + y).reshape(-1, 3)
        R, c = self._frame(xD)
        return (n - self.c0) @ R.T + c

    def jacobian(self, q, xD):
        q = np.asarray(q, dtype=np.float64)
        y, Jy = self._correction(q, True)
        n = (self.X + self.E @ q + y).reshape(-1, 3)
        R, c = self._frame(xD)
        Jn = (self.E + Jy).reshape(-1, 3, self.dim)
        J = np.einsum("ij,njr->nir", R, Jn).reshape(-1, self.dim)
        return (n - self.c0) @ R.T + c, J

    def project(self, x, xD) -> np.ndarray:
        """Modal coordinates of positions x (n,3): least squares on the linear part (l^T y = 0)."""
        R, c = self._frame(xD)
        u = ((np.asarray(x) - c) @ R + self.c0).reshape(-1) - self.X
        return np.linalg.lstsq(self.E, u, rcond=None)[0]


# --------------------------------------------------------------------------------------------------
# the subspace-dynamics study (Sec. 4.5) and keyframing (Fig. 6)
# --------------------------------------------------------------------------------------------------
def relative_errors(positions, reference, diagonal: float) -> np.ndarray:
    """(T,) RMS vertex distance between two motions (T,n,3) per frame, over ``diagonal`` (NaN where either is)."""
    d = np.asarray(positions, dtype=np.float64) - np.asarray(reference, dtype=np.float64)
    return np.sqrt((d**2).sum(-1).mean(-1)) / diagonal


def first_test_sequence(f) -> str:
    """Name of the first sequence of split ``test`` in an open trajectories.h5."""
    for name, g in f["sequences"].items():
        if g.attrs.get("split") == "test":
            return name
    raise ValueError(f"{f.filename}: no test sequence to replay (sequences: {sorted(f['sequences'])})")


def subspace_dynamics(f, model: NeuralModes, box: float, settings: dict, full: dict, progress: bool = False) -> dict:
    """Replay the first test sequence's Dirichlet motion in the Neural Modes and linear-modes subspaces.

    Parameters
    ----------
    f : the scene's open trajectories.h5 (potential, rest state, the full simulation to compare with).
    model : trained Neural Modes of the scene (Dirichlet modes).
    box : the modal training box; the cubature's poses are drawn in it (data-free, like the modes).
    settings : ``frames`` (0: all), ``max_iterations`` per step, ``cubature_tolerance``,
        ``cubature_samples`` (and half as many held out), ``cubature_max_elements``.
    full : the full-space Newton frame of the same sequence timed in the same process
        (``latent.timing.time_full_space`` of :func:`first_test_sequence`): full_ms, full_iterations,
        full_frames_timed.

    Every method of ``labels.DYNAMICS_METHODS`` steps the reduced implicit Euler of Eq. 15
    (``reduced.reduced_rollout``) from rest.  Returns ``sequence``, ``reference`` (T,n,3),
    ``dirichlet_positions``, ``full`` (timing), ``cubatures`` {neural|linear: Cubature}, ``runs`` {slug:
    reduced_rollout's dict + ``error`` (T,)} and ``rows`` (a DataFrame, the full-space row first).
    """
    pot = potential_from_artefact(f)
    name = first_test_sequence(f)
    g = f["sequences"][name]
    T = int(settings["frames"]) or g["positions"].shape[0]
    ref, xD = g["positions"][:T], g["dirichlet_positions"][:T]
    if len(ref) < 3:
        raise ValueError(f"{f.filename}: sequence {name!r} has {len(ref)} frames; the dynamics study needs at least 3")
    X = f["rest_positions"][()]
    diag = bbox_diagonal(X)
    D = pot.dirichlet.numpy()
    subspaces = {"neural": NeuralModesSubspace(model, D), "linear": NeuralModesSubspace(model, D, linear_only=True)}
    cubatures, stepping = {}, {}
    count = int(settings["cubature_samples"])
    for kind, sub in subspaces.items():
        c = fit_cubature(
            pot.terms, sub, box_samples(sub.dim, box, count, seed=0), float(settings["cubature_tolerance"]),
            int(settings["cubature_max_elements"]), validation=box_samples(sub.dim, box, max(count // 2, 1), seed=1),
        )  # fmt: skip
        cubatures[kind], stepping[kind] = c, cubature_potential(pot, c)
        log.info("%s modes: cubature of %d of %d elements, force error %.4f (held out %.4f), %.1f s",
                 kind, len(c.index), c.n_elements, c.train_error, c.validation_error, c.fit_seconds)  # fmt: skip
    elements = sum(int(t.stencils.shape[0]) for t in pot.terms)
    zero = relative_errors(ref, ref, diag)  # the full simulation against itself
    rows = [{"method": "full space, Newton", "elements": elements, "steps": full["full_frames_timed"], "ms/step median": full["full_ms"],
             "ms/step mean": full["full_ms"], "iterations/step": full["full_iterations"], "error mean": float(zero.mean()),
             "error max": float(zero.max()), "diverged frame": -1}]  # fmt: skip
    runs = {}
    for slug in tqdm(DYNAMICS_METHODS, desc="subspace dynamics", disable=not progress, leave=False):
        label, linear, method, cubature = DYNAMICS_METHODS[slug]
        kind = "linear" if linear else "neural"
        q0 = np.zeros(model.m)
        rs = ReducedSettings(method=method, max_iterations=int(settings["max_iterations"]))
        out = reduced_rollout(subspaces[kind], stepping[kind] if cubature else pot, q0, q0, xD, rs)
        out["error"] = relative_errors(out["positions"], ref, diag)
        runs[slug] = out
        rows.append({"method": label, "elements": len(cubatures[kind].index) if cubature else elements, **_row(out, method)})
        r = rows[-1]
        log.info("%s: %.2f ms/step, error mean %.4f max %.4f, diverged at %d", label, r["ms/step median"], r["error mean"], r["error max"], r["diverged frame"])
    return {"sequence": name, "reference": ref, "dirichlet_positions": xD, "full": full, "cubatures": cubatures, "runs": runs, "rows": pd.DataFrame(rows)}


def _row(out: dict, method: str) -> dict:
    """A table row of one reduced rollout: medians and means over its steps (frames 2 on), errors over its
    frames before divergence; the split of a step only for Newton (L-BFGS does not split its step)."""
    steps = out["step_ms"][2:]
    ms = steps[np.isfinite(steps)]
    ok = np.isfinite(out["error"])
    row = {
        "steps": len(ms), "ms/step median": float(np.median(ms)) if len(ms) else np.nan, "ms/step mean": float(ms.mean()) if len(ms) else np.nan,
        "iterations/step": float(out["iterations"][2:].mean()), "error mean": float(out["error"][ok].mean()), "error max": float(out["error"][ok].max()),
        "diverged frame": int(out["diverged_frame"]),
    }  # fmt: skip
    for part in ("map", "derivatives", "reduce", "line_search"):
        v = out[f"{part}_ms"][2:]
        row[f"{part.replace('_', ' ')} ms"] = float(np.nanmedian(v)) if method == "newton" and np.isfinite(v).any() else np.nan
    return row


def keyframe_coordinates(poses, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of modal coordinates between keyframes (Fig. 6).

    ``poses`` (K,m) keyframes, ``steps`` >= 1 frames from one keyframe to the next.  Returns z
    ((K-1) steps + 1, m) and the frame of each keyframe (K,), where z equals the keyframe exactly.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or len(poses) < 2 or steps < 1:
        raise ValueError(f"keyframe_coordinates: need at least two keyframes (K,m) and steps >= 1, got shape {poses.shape}, steps {steps}")
    t = np.arange(steps) / steps
    z = np.concatenate([(1 - t)[:, None] * a + t[:, None] * b for a, b in zip(poses[:-1], poses[1:])] + [poses[-1:]])
    keys = np.arange(len(poses)) * steps
    z[keys] = poses  # exact, not 1 * a + 0 * b
    return z, keys

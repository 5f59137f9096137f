"""Motions read from trajectory files: one sequence of the ground truth or of a rollout.

Trajectory layout (``docs/artefacts.md``; ground truth ``trajectories.h5`` and
rollouts ``rollout.h5`` alike): root ``rest_positions``, ``dirichlet``, the
model's connectivity (``edges``, ``triangles`` or ``tets``/``surface``),
attributes ``model``, ``dt``, ``gravity``; ``/sequences/<name>/positions
(T,n,3)``, attribute ``diverged_frame`` on rollouts.  :func:`load_motion`
reads one sequence (or chosen frames of it) into a :class:`Motion`, which
:mod:`latentsim.report.render` draws and :mod:`latentsim.report.paraview`
compares against.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from latentsim.io import ArtefactError, open_artefact, require
from latentsim.mesh import surface_of

__all__ = ["MODEL_CELLS", "Motion", "load_motion", "model_of"]

# connectivity each model needs (first match wins for tets: a stored surface saves recomputing it)
MODEL_CELLS = {"rods": ("edges",), "shell": ("triangles",), "tets": ("surface", "tets")}


def model_of(h5, h5_path) -> str:
    """The root attribute ``model`` of an open trajectory file (a key of :data:`MODEL_CELLS`).

    Raises
    ------
    ArtefactError
        Naming the file, where the attribute is missing or names no known model.
    """
    model = str(h5.attrs.get("model", ""))
    if model not in MODEL_CELLS:
        raise ArtefactError(f"{h5_path}: root attribute 'model' is {model!r}; expected one of {sorted(MODEL_CELLS)}")
    return model


@dataclass
class Motion:
    """One sequence of a trajectory-layout file, possibly a subset of its frames.

    Attributes
    ----------
    label : str, what panels call it (method name or "ground truth").
    sequence : str
    model : str, ``rods``, ``shell`` or ``tets``.
    positions : (k,n,3) float, the loaded frames (NaN after divergence).
    frames : (k,) int, frame index of each loaded position.
    n_frames : int, frames in the file's sequence.
    rest : (n,3) float, rest positions.
    dirichlet : (m,) int, prescribed vertices.
    segments : (E,2) int or None, rod edges (polylines).
    triangles : (F,3) int or None, shell triangles or the tets' boundary faces.
    dt : float
    diverged_frame : int, first diverged frame, -1 when stable (or unknown).
    vertical : int, axis drawn upwards (that of the root ``gravity``; y when absent).
    """

    label: str
    sequence: str
    model: str
    positions: np.ndarray
    frames: np.ndarray
    n_frames: int
    rest: np.ndarray
    dirichlet: np.ndarray
    segments: np.ndarray | None
    triangles: np.ndarray | None
    dt: float
    diverged_frame: int = -1
    vertical: int = 1

    def at(self, frame: int):
        """Positions (n,3) at ``frame``, or None when not loaded / past the end."""
        k = np.flatnonzero(self.frames == frame)
        return self.positions[k[0]] if len(k) else None

    def status(self, frame: int) -> str:
        """``ok``, ``diverged`` (at or after divergence, or non-finite) or ``missing``."""
        if frame >= self.n_frames:
            return "missing"
        if 0 <= self.diverged_frame <= frame:
            return "diverged"
        x = self.at(frame)
        if x is None:
            return "missing"
        return "ok" if np.isfinite(x).all() else "diverged"


def load_motion(h5_path, sequence: str, frames=None, label=None) -> Motion:
    """Read one sequence of a trajectory-layout file.

    Parameters
    ----------
    h5_path : path of ``trajectories.h5``, ``rollout.h5`` or any file of that layout.
    sequence : str, group name under ``/sequences``.
    frames : iterable of int or None
        Frames to read (those past the sequence's end are skipped); all when None.
    label : str, defaults to the file's ``method`` attribute or its path.

    Raises
    ------
    ArtefactError
        Naming the file and the missing key (sequence, positions, connectivity).
    """
    h5_path = str(h5_path)
    with open_artefact(h5_path) as f:
        seqs = require(f, "sequences", path=h5_path)
        if sequence not in seqs:
            raise ArtefactError(f"{h5_path}: no sequence '{sequence}'; has {sorted(seqs)}")
        g = seqs[sequence]
        ds = require(g, "positions", path=h5_path)
        T = ds.shape[0]
        if frames is None:
            idx = np.arange(T)
            pos = ds[()]
        else:
            idx = np.unique(np.asarray(list(frames), dtype=np.int64))
            if (idx < 0).any():
                raise ValueError(f"{h5_path}: negative frame in {idx.tolist()}")
            idx = idx[idx < T]
            pos = ds[idx] if len(idx) else np.zeros((0,) + ds.shape[1:])
        model = model_of(f, h5_path)
        segments = triangles = None
        if model == "rods":
            segments = require(f, "edges", path=h5_path)[()]
        elif model == "shell":
            triangles = require(f, "triangles", path=h5_path)[()]
        else:
            triangles = f["surface"][()] if "surface" in f else surface_of(require(f, "tets", path=h5_path)[()])
        rest = f["rest_positions"][()] if "rest_positions" in f else ds[0]
        dirichlet = f["dirichlet"][()] if "dirichlet" in f else np.zeros(0, dtype=np.int64)
        div = int(g.attrs.get("diverged_frame", -1))
        if label is None:
            label = str(g.attrs.get("method", f.attrs.get("method", Path(h5_path).parent.name)))
        dt = float(f.attrs.get("dt", 1.0))
        g_vec = np.asarray(f.attrs.get("gravity", [0.0, -1.0, 0.0]), dtype=float).ravel()
        vertical = int(np.argmax(np.abs(g_vec))) if g_vec.size == 3 and np.abs(g_vec).max() > 0 else 1
    return Motion(
        label, sequence, model, np.asarray(pos, float), idx, T, rest, dirichlet, segments, triangles, dt, div, vertical
    )


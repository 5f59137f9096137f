"""A trained model as a user steps it: encode two full-space frames, then step frame after frame.

:func:`load` reads a rollout folder's ``runtime.npz`` (``results/rollout/{scene}/{method}/seed{k}/``)
into a :class:`TrainedModel`, which keeps the latent state that a
:class:`latentsim.runtime.Stepper` takes as arguments (the two previous latents and boundary
parameters) and speaks in full-space positions::

    model = latentsim.runtime.load("results/rollout/tiny_rods/self_supervised/seed0")
    model.encode(x0, x1, xD[:2], p[:2])          # frames 0 and 1: (n, 3) each
    for t in range(2, T):
        x = model.step(p[t], xD[t])               # frame t: (n, 3) float64

Frame t is Li et al. 2025 Eq. 3 and the decode, from the boundary-condition parameters
p_t, p_{t-1}, p_{t-2} (k,) and the prescribed Dirichlet positions x*_D,t (m, 3)::

    z_t = integrate(z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}),   x_t = decode(z_t, x*_D,t)

as the rollout stage does (there in PyTorch, here in NumPy: the same frames to float32 rounding).
"""

from __future__ import annotations

import os

import numpy as np

from latentsim.runtime.files import read_runtime
from latentsim.runtime.frame import RigidFrameStepper, frame_inputs
from latentsim.runtime.numpy_stepper import NumpyStepper
from latentsim.runtime.stepper import Stepper

__all__ = ["RUNTIME_FILE", "TrainedModel", "load"]

RUNTIME_FILE = "runtime.npz"  # the rollout stage writes it beside rollout.h5


def load(path, dtype=np.float32) -> TrainedModel:
    """The :class:`TrainedModel` of a rollout folder (holding ``runtime.npz``) or of a ``runtime.npz`` file.

    Parameters
    ----------
    path : ``results/rollout/{scene}/{method}/seed{k}/`` or the ``runtime.npz`` in it.
    dtype : the networks' dtype, ``np.float32`` (default, as trained) or ``np.float64``.

    Steps with :class:`latentsim.runtime.NumpyStepper`; for one numba kernel call per frame,
    ``TrainedModel(latentsim.runtime.compiled.load_runtime(path))``.
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        path = os.path.join(path, RUNTIME_FILE)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: no such runtime file (the rollout stage writes results/rollout/<scene>/<method>/seed<k>/{RUNTIME_FILE})")
    if not path.endswith(".npz"):
        raise ValueError(f"{path}: a runtime is a .npz file (a .pt/.pt2 torch.export program is the step alone: torch.export.load(path).module())")
    return TrainedModel(NumpyStepper(read_runtime(path), dtype, source=path))


class TrainedModel:
    """A trained latent model stepping full-space frames (:func:`load` makes one).

    Parameters
    ----------
    stepper : a :class:`latentsim.runtime.Stepper` that takes NumPy arrays and has ``encode``
        (:class:`latentsim.runtime.NumpyStepper` or :class:`latentsim.runtime.compiled.CompiledStepper`).

    Attributes
    ----------
    r, k, n, m : latent dimension, boundary-condition parameters per frame, vertices, Dirichlet vertices.
    origin : whether the integrator was trained with ``integrator.origin_input``: it takes the frame's mean
        Dirichlet position after p, which the model appends from xD (``k`` does not count it).
    rigid : whether the autoencoder encodes positions in the frame that turns with the prescribed vertices
        (``autoencoder.rigid_frame``): the model carries p and the positions into the frame at each frame's
        xD and back (:mod:`latentsim.runtime.frame`; ``k`` counts p as the user gives it).
    dirichlet : (m,) the Dirichlet vertices, in the order of the Dirichlet positions xD.
    stepper : the stepper; ``stepper.header`` the runtime file's header.

    State: the latents z_{t-1}, z_{t-2} (r,), parameters p_{t-1}, p_{t-2} (k,) and Dirichlet
    positions x*_D,t-1 (m, 3) of the last two frames, set by :meth:`encode` (or :meth:`start`)
    and advanced by :meth:`step`.
    """

    def __init__(self, stepper: Stepper):
        header = getattr(stepper, "header", {})
        # a model encoded in a rigid frame decodes in it (runtime.frame): its stepper carries positions in and out
        self.rigid = "rigid_frame" in header
        if self.rigid and not isinstance(stepper, RigidFrameStepper):
            stepper = RigidFrameStepper(stepper, header["rigid_frame"]["vertices"], header["rigid_frame"]["rest_frame"])
        self.stepper = stepper
        # an integrator trained with the origin input takes the mean Dirichlet position after p: appended here
        hparams = header.get("integrator_hparams", {})
        self.origin = bool(hparams.get("origin", False))
        self.r, self.k, self.n = stepper.r, stepper.k - 3 * self.origin - 9 * self.rigid, stepper.n
        self.dirichlet = np.asarray(stepper.dirichlet, dtype=np.int64)
        self.m = len(self.dirichlet)
        dt = stepper.dtype
        self._z = np.full((2, self.r), np.nan, dtype=dt)  # z_{t-1}, z_{t-2}
        self._p = np.full((2, stepper.k), np.nan, dtype=dt)  # p_{t-1}, p_{t-2} as the integrator takes them
        self._znew = np.empty(self.r, dtype=dt)
        self._pnew = np.empty(stepper.k, dtype=dt)
        self._xD = np.full((self.m, 3), np.nan)  # x*_D of the last frame
        self.frame = -1  # the last frame's index (1 after encode/start)

    @property
    def latent(self) -> np.ndarray:
        """z of the last frame (r,) (a copy)."""
        return self._z[0].copy()

    def _frame_args(self, p, xD, name: str):
        """p as the integrator takes it and xD (float64), checked; with a rigid frame also its pose at xD
        (``self._pose``, which the step's decode reuses)."""
        p = np.asarray(p, dtype=self.stepper.dtype)
        xD = np.ascontiguousarray(xD, dtype=np.float64)
        want = (2, self.k) if name == "start" else (self.k,)  # start: frames 0 and 1
        if p.shape != want:
            raise ValueError(f"{name}: boundary parameters p need shape {want}, got {p.shape}")
        if xD.shape[-2:] != (self.m, 3):
            raise ValueError(f"{name}: Dirichlet positions xD need shape ({self.m}, 3), got {xD.shape}")
        if self.rigid:  # p's 3-vectors in the frame, then the frame's R^T (latent.boundary_inputs)
            self._pose = self.stepper.pose(np.broadcast_to(xD, p.shape[:-1] + xD.shape[-2:]))
            p = frame_inputs(p.astype(np.float64), self._pose[0]).astype(p.dtype)
        if self.origin:  # the integrator's p ends with the mean Dirichlet position (latent.boundary_inputs)
            mean = np.broadcast_to(xD.mean(-2), p.shape[:-1] + (3,)).astype(p.dtype)
            p = np.concatenate([p, mean], -1)
        return p, xD

    def start(self, z0, z1, p, xD) -> None:
        """Set the state from the latents z0, z1 (r,) of frames 0 and 1 (e.g. ``rollout.h5``'s first two
        ``latents``), their boundary parameters p (2, k) and the Dirichlet positions of frame 1 (m, 3)
        (or of frames 0 and 1, (2, m, 3))."""
        p, xD = self._frame_args(p, xD, "start")
        z = np.asarray([z0, z1], dtype=self.stepper.dtype)
        if z.shape != (2, self.r):
            raise ValueError(f"start: latents need shape ({self.r},) each, got {z.shape[1:]}")
        self._z[:] = z[::-1]
        self._p[:] = p[::-1]
        self._xD[:] = xD[-1] if xD.ndim == 3 else xD
        self.frame = 1

    def encode(self, x0, x1, xD, p) -> np.ndarray:
        """Encode frames 0 and 1 and start from them; returns their latents (2, r).

        Parameters
        ----------
        x0, x1 : (n, 3) full-space positions of two consecutive frames.
        xD : (m, 3) Dirichlet positions of both, or (2, m, 3) of each (the prescribed vertices'
            positions, in the order of :attr:`dirichlet`).
        p : (2, k) the boundary-condition parameters of frames 0 and 1 (the integrator reads
            p_{t-1} and p_{t-2} at the first step).
        """
        xD = np.asarray(xD, dtype=np.float64)
        xD2 = np.broadcast_to(xD, (2,) + xD.shape[-2:]) if xD.ndim == 2 else xD
        if xD2.shape != (2, self.m, 3):
            raise ValueError(f"encode: Dirichlet positions xD need shape ({self.m}, 3) or (2, {self.m}, 3), got {xD.shape}")
        z = self.stepper.encode(np.stack([np.asarray(x0, dtype=np.float64), np.asarray(x1, dtype=np.float64)]), xD2)
        self.start(z[0], z[1], p, xD2)
        return z.copy()

    def step(self, p, xD=None) -> np.ndarray:
        """The next frame's positions (n, 3) float64 (a new array) for its boundary parameters p (k,) and
        Dirichlet positions xD (m, 3) (None: those of the last frame, a boundary at rest)."""
        if self.frame < 1:
            raise RuntimeError("step: no state yet; encode two frames (or start from two latents) first")
        p, xD = self._frame_args(p, self._xD if xD is None else xD, "step")
        np.copyto(self._pnew, p)
        st = self.stepper
        pose = {"pose": self._pose} if self.rigid else {}  # the frame that p was carried into
        z, x = st.step(self._z[0], self._z[1], self._pnew, self._p[0], self._p[1], xD, z_out=self._znew, **pose)
        self._z[1] = self._z[0]
        self._z[0] = z
        self._p[1] = self._p[0]
        self._p[0] = self._pnew
        self._xD[:] = xD
        self.frame += 1
        return np.array(x)

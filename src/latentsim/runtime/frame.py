"""The rigid frame that turns with a scene's prescribed vertices (``autoencoder.rigid_frame``; not in
the paper), for NumPy arrays and tensors alike: the pipeline's coordinates
(:class:`latentsim.latent.RelativeCoordinates`) and integrator inputs
(:func:`latentsim.latent.integrator.boundary_inputs`) and the deployable runtime use these functions.

A frame is R = F(x*_D) F(x*_D,rest)^T, F the orthonormal frame of three prescribed vertices
(:func:`orthonormal_frame`), about the mean prescribed position c: a vector u of the encoded space is
R u + c in the world.  :class:`RigidFrameStepper` runs any :class:`~latentsim.runtime.Stepper` of a
model encoded in such a frame: it decodes in the frame and carries the positions out.
"""

from __future__ import annotations

import numpy as np

__all__ = ["RigidFrameStepper", "frame_inputs", "frame_pose", "orthonormal_frame"]


def _stack(arrays, axis: int):
    if type(arrays[0]).__module__.split(".")[0] != "torch":  # NumPy arrays (or their scalars)
        return np.stack(arrays, axis)
    import torch  # a tensor's caller has torch

    return torch.stack(arrays, axis)


def _norm(v):
    return ((v * v).sum(-1) ** 0.5)[..., None]


def orthonormal_frame(p):
    """The right-handed orthonormal frame (..., 3, 3) (columns e1, e2, e3) of three points p (..., 3, 3):
    e1 along p1 - p0, e2 in their plane towards p2 (Gram-Schmidt), e3 = e1 x e2.  A rigid motion of the
    points turns the frame with them."""
    if isinstance(p, np.ndarray) and p.ndim == 2:  # one frame (a runtime's step): in Python floats, a few microseconds
        (ax, ay, az), (bx, by, bz), (cx, cy, cz) = p.tolist()
        ux, uy, uz = bx - ax, by - ay, bz - az
        n = (ux * ux + uy * uy + uz * uz) ** 0.5
        ux, uy, uz = ux / n, uy / n, uz / n
        wx, wy, wz = cx - ax, cy - ay, cz - az
        d = wx * ux + wy * uy + wz * uz
        wx, wy, wz = wx - d * ux, wy - d * uy, wz - d * uz
        n = (wx * wx + wy * wy + wz * wz) ** 0.5
        wx, wy, wz = wx / n, wy / n, wz / n
        return np.array([[ux, wx, uy * wz - uz * wy], [uy, wy, uz * wx - ux * wz], [uz, wz, ux * wy - uy * wx]])
    a, b, c = p[..., 0, :], p[..., 1, :], p[..., 2, :]
    e1 = (b - a) / _norm(b - a)
    w = (c - a) - ((c - a) * e1).sum(-1)[..., None] * e1
    e2 = w / _norm(w)
    x1, y1, z1 = e1[..., 0], e1[..., 1], e1[..., 2]
    x2, y2, z2 = e2[..., 0], e2[..., 1], e2[..., 2]
    e3 = _stack([y1 * z2 - z1 * y2, z1 * x2 - x1 * z2, x1 * y2 - y1 * x2], -1)
    return _stack([e1, e2, e3], -1)


def frame_pose(xD, vertices, rest_frame):
    """R (..., 3, 3) and c (..., 1, 3) of the frame at prescribed positions xD (..., m, 3): ``vertices``
    the three positions in the Dirichlet list that span it, ``rest_frame`` (3, 3) their frame at rest."""
    if isinstance(xD, np.ndarray) and xD.ndim == 2:  # one frame (a runtime's step): a dot for the mean, 1 us against 5
        R = orthonormal_frame(xD.take(vertices, axis=0)) @ rest_frame.T
        return R, np.dot(np.full(len(xD), 1.0 / len(xD)), xD)[None, :]
    R = orthonormal_frame(xD[..., list(vertices), :]) @ rest_frame.swapaxes(-1, -2)
    return R, xD.mean(-2)[..., None, :]


def frame_inputs(p, R):
    """Boundary-condition parameters p (..., k) (3-vectors: a program's velocity and angular velocity) as
    an integrator in the frame R (..., 3, 3) takes them: each 3-vector carried into the frame, R^T v, then
    the nine entries of R^T row by row (..., k + 9)."""
    if p.shape[-1] % 3:
        raise ValueError(f"boundary inputs in a rigid frame: {p.shape[-1]} parameters per frame are not 3-vectors")
    Rt = R.swapaxes(-1, -2)
    turned = (Rt[..., None, :, :] @ p.reshape(p.shape[:-1] + (-1, 3, 1)))[..., 0]
    flat = [turned.reshape(p.shape), Rt.reshape(Rt.shape[:-2] + (9,))]
    if isinstance(p, np.ndarray):
        return np.concatenate(flat, -1)
    import torch

    return torch.cat(flat, -1)


class RigidFrameStepper:
    """A :class:`~latentsim.runtime.Stepper` of a model encoded in a rigid frame, around the stepper
    ``inner`` of its networks: integration as ``inner``'s (its p already in the frame,
    :func:`frame_inputs`), decoding in the frame at the prescribed positions carried into it,
    (x*_D - c) R, and the positions carried out, x R^T + c (float64 NumPy arrays).

    ``vertices``, ``rest_frame``: the runtime header's ``rigid_frame`` (:func:`frame_pose`)."""

    def __init__(self, inner, vertices, rest_frame):
        self.inner = inner
        self.vertices = [int(v) for v in vertices]
        self.rest_frame = np.asarray(rest_frame, dtype=np.float64).reshape(3, 3)
        self.r, self.k, self.n, self.dtype = inner.r, inner.k, inner.n, inner.dtype
        self._carry = getattr(inner, "carry_out", None)  # a compiled stepper carries the positions out in its kernel

    def __getattr__(self, name):  # the rest (header, dirichlet, ...) as the inner stepper's
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def pose(self, xD):
        """R, c of the frame at prescribed positions xD (..., m, 3) (:func:`frame_pose`)."""
        return frame_pose(np.asarray(xD, dtype=np.float64), self.vertices, self.rest_frame)

    def local(self, x, xD, pose=None):
        """Positions x (..., n, 3) (or None) and prescribed xD (..., m, 3) carried into the frame; and R, c
        (``pose``: R, c already found at this xD, as :class:`~latentsim.runtime.TrainedModel` finds them for p)."""
        xD = np.asarray(xD, dtype=np.float64)
        R, c = self.pose(xD) if pose is None else pose
        return (None if x is None else (np.asarray(x, dtype=np.float64) - c) @ R), (xD - c) @ R, R, c

    def inputs(self, z_prev, z_prev2, p, p_prev, p_prev2, xD):
        return self.inner.inputs(z_prev, z_prev2, p, p_prev, p_prev2, xD)

    def integrate(self, z_prev, z_prev2, p, p_prev, p_prev2, out=None):
        return self.inner.integrate(z_prev, z_prev2, p, p_prev, p_prev2, out=out)

    def decode(self, z, xD, out=None, pose=None):
        _, xl, R, c = self.local(None, xD, pose)
        if not isinstance(xD, np.ndarray):  # a stepper of tensors takes its own type
            xl = xD.new_tensor(xl)
        if self._carry is not None:  # decoded into out, carried out in one pass
            if out is None:
                out = np.empty((self.n, 3))
            return self._carry(self.inner.decode(z, xl, out=out), R, c)
        x = np.asarray(self.inner.decode(z, xl))
        out = np.matmul(x, R.swapaxes(-1, -2), out=out)
        out += c
        return out

    def step(self, z_prev, z_prev2, p, p_prev, p_prev2, xD, z_out=None, x_out=None, pose=None):
        z = self.integrate(z_prev, z_prev2, p, p_prev, p_prev2, out=z_out)
        return z, self.decode(z, xD, out=x_out, pose=pose)

    def encode(self, x, xD):
        """Latents of positions x (..., n, 3) with prescribed xD (..., m, 3), encoded in the frame."""
        xl, xDl, _, _ = self.local(x, xD)
        return self.inner.encode(xl, xDl)

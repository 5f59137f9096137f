"""Same-run timings behind the speed-ups (Li et al. 2025, Table 2): one latent step with each
runtime stepper, one decoded vertex's Jacobian-vector product, and full-space Newton frames timed
in the same process, so that a speed-up is a ratio of two numbers measured side by side.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from latentsim import runtime
from latentsim.io import require
from latentsim.latent.autoencoder import decode_latents
from latentsim.scene import potential_from_artefact
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings


class EagerStepper(runtime.TorchStepper):
    """The training modules themselves (eval mode): the eager-PyTorch baseline of
    :func:`latentsim.runtime.time_step`, beside the folded runtimes."""

    def __init__(self, ae, integrator, coords):
        self.ae, self.integrator, self.coords = ae.eval(), integrator.eval(), coords
        dtype = next(integrator.parameters()).dtype
        super().__init__(self._integrate_frame, self._decode_frame, ae.latent_dim, integrator.bc_dim, coords.n, dtype)

    def _integrate_frame(self, z_prev, z_prev2, p, p_prev, p_prev2):
        return self.integrator(z_prev[None], z_prev2[None], p[None], p_prev[None], p_prev2[None])[0]

    def _decode_frame(self, z, xD):
        return decode_latents(self.ae, self.coords, z[None], xD[None])[0]


def rigid_frame_steppers(steppers: dict, coords) -> dict:
    """``steppers`` as they step a model whose coordinates have a rigid frame (``coords.rigid``): each folded
    runtime inside a :class:`~latentsim.runtime.RigidFrameStepper`, so that its timing includes carrying the
    positions out of the frame (the eager one decodes through ``coords`` already); as they are otherwise."""
    if not coords.rigid:
        return steppers
    rest = coords.rest_frame.numpy()
    return {k: st if isinstance(st, EagerStepper) else runtime.RigidFrameStepper(st, coords.frame_vertices, rest) for k, st in steppers.items()}


def time_steppers(steppers: dict, z1, z0, p, xD, repeats: int) -> dict:
    """Median ms of one latent step with each stepper (``{name}_step_ms`` etc.).

    ``step_ms``, ``integrate_ms`` and ``decode_ms`` are those of the fastest
    stepper (whose name is ``runtime``), the deployable path.  ``floor_ms``: where a
    stepper offers it (the compiled one, :meth:`~latentsim.runtime.compiled.CompiledStepper.output_pass`),
    one bare pass of the model's own output layer over every DoF, timed in the same rounds'
    process: the floor under any step of this model.
    """
    out: dict = {}
    for name, st in steppers.items():
        r = runtime.time_step(st, z1, z0, p, p, p, xD, repeats=repeats)  # each stepper converts the frame itself
        for k, v in r.items():
            out[f"{name}_{k}"] = v
    best = min(steppers, key=lambda n: out[f"{n}_step_ms"])
    out.update(step_ms=out[f"{best}_step_ms"], integrate_ms=out[f"{best}_integrate_ms"], decode_ms=out[f"{best}_decode_ms"])
    out["runtime"] = best
    floor = next((st for st in steppers.values() if hasattr(st, "output_pass")), None)
    if floor is not None:
        out["floor_ms"] = runtime.time_jvp(floor.output_pass()[0], repeats)
    return out


def time_jvps(ae, stepper, coords, z, repeats: int) -> dict:
    """Li et al. Table 2: one decoded vertex's Jacobian-vector product w.r.t. the latent, timed two ways.

    ``jvp_torch_ms``: ``torch.func.jvp`` of the PyTorch decoder restricted to
    the vertex (as the paper did); ``jvp_forward_ms``: the hand-written forward
    mode of the NumPy runtime.  The vertex is the free vertex farthest down the
    encoded vector (any free vertex costs the same).
    """
    v = torch.ones_like(torch.as_tensor(z, dtype=torch.float32))
    free = np.setdiff1d(np.arange(coords.n), coords.dirichlet.numpy())
    vertex = int(free[-1])
    row = stepper._row_of_vertex(vertex)
    zt = torch.as_tensor(z, dtype=torch.float32)
    zn, vn = np.asarray(z, dtype=np.float32), v.numpy()
    return {
        "jvp_torch_ms": runtime.time_jvp(lambda: runtime.jvp_vertex_torch(ae, zt, v, row), repeats),
        "jvp_forward_ms": runtime.time_jvp(lambda: stepper.jvp_vertex(zn, vn, vertex), repeats),
    }


def time_full_space(f, sequence: str, frames: int = 20) -> dict:
    """Mean wall time [ms] of full-space Newton frames, timed now (for same-run ratios).

    Steps ``frames`` frames spread evenly over ``sequence`` of an open
    trajectories.h5, each from the stored ground-truth states, with the
    simulator's own solver settings (tolerance from the file).  Spread and
    averaged like the simulator's own ms/frame: a sequence that settles (the
    cantilever's sag) has cheap frames at rest and dear ones while it moves,
    and a window in its middle would see only one kind.
    """
    pot = potential_from_artefact(f, free_only=True)
    tol = float(f.attrs.get("newton_tolerance", 1e-6))
    solver = ImplicitEuler(pot, NewtonSettings(tolerance=tol))
    g = require(f, "sequences")[sequence]
    x, xD = g["positions"], g["dirichlet_positions"]
    T = x.shape[0]
    if T < 3:
        raise ValueError(f"sequence {sequence}: {T} frames, need at least 3 to time a full-space step")
    solver.step(x[1], x[0], xD[2])  # warm-up: first-call costs (JIT, caches)
    ms, iters = [], []
    for t in np.unique(np.linspace(2, T - 1, max(1, frames)).round().astype(int)):
        start = time.perf_counter()
        _, info = solver.step(x[t - 1], x[t - 2], xD[t])
        ms.append(1e3 * (time.perf_counter() - start))
        iters.append(info.iterations)
    return {"full_ms": float(np.mean(ms)), "full_iterations": float(np.mean(iters)), "full_frames_timed": len(ms)}



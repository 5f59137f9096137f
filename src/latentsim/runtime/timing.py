"""Wall-clock timing of the latent runtimes (Li et al. 2025, Table 2: step and Jvp costs).

:func:`time_step` times any :class:`latentsim.runtime.Stepper` (each converts the frame's
arrays itself); :func:`time_jvp` any callable; :func:`jvp_vertex_torch` is the paper's
single-vertex Jacobian-vector product, ``torch.func.jvp`` of the PyTorch decoder.
"""

from __future__ import annotations

import time

import numpy as np
import torch

__all__ = ["jvp_vertex_torch", "time_jvp", "time_step"]


def _median_ms(samples) -> float:
    return float(np.median(np.asarray(samples)) * 1e3)


def time_step(stepper, z_prev, z_prev2, p, p_prev, p_prev2, xD, repeats: int = 200, warmup: int = 10) -> dict:
    """Median wall time [ms] of integration, decoding and the whole step of one frame.

    The frame's arrays (NumPy arrays or tensors) go through ``stepper.inputs`` first,
    outside the timing.  ``step_ms`` times one whole :meth:`step` call (not the sum
    of the two halves' medians).
    """
    args = stepper.inputs(z_prev, z_prev2, p, p_prev, p_prev2, xD)
    z_t = stepper.integrate(*args[:5])
    z = stepper.inputs(z_t, *args[1:])[0]  # z_t in an array of its own (a stepper may return its buffer)
    xD = args[5]
    ti, td, ts = [], [], []
    for i in range(max(int(repeats), 1) + warmup):
        t0 = time.perf_counter()
        stepper.integrate(*args[:5])
        t1 = time.perf_counter()
        stepper.decode(z, xD)
        t2 = time.perf_counter()
        stepper.step(*args)
        t3 = time.perf_counter()
        if i >= warmup:
            ti.append(t1 - t0)
            td.append(t2 - t1)
            ts.append(t3 - t2)
    return {"integrate_ms": _median_ms(ti), "decode_ms": _median_ms(td), "step_ms": _median_ms(ts)}


def jvp_vertex_torch(ae, z: torch.Tensor, v: torch.Tensor, vertex_row: int):
    """The paper's Jvp (Li et al. Table 2): ``torch.func.jvp`` of the decoder,
    restricted to the 3 outputs of one vertex (row ``vertex_row`` of the
    encoded vector).  z, v : (r,).  Returns (u_v, du_v), each (3,)."""
    rows = slice(3 * vertex_row, 3 * vertex_row + 3)

    def f(zz):
        return ae.decode(zz[None])[0, rows]

    return torch.func.jvp(f, (z,), (v,))


def time_jvp(fn, repeats: int = 200, warmup: int = 10) -> float:
    """Median wall time [ms] of ``fn()``."""
    samples = []
    for i in range(max(int(repeats), 1) + warmup):
        t0 = time.perf_counter()
        fn()
        if i >= warmup:
            samples.append(time.perf_counter() - t0)
    return _median_ms(samples)

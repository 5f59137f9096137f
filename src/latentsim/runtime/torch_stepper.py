"""PyTorch latent runtimes: the folded step exported with ``torch.export``, and eager PyTorch.

The folded layers (:mod:`latentsim.runtime.fold`) as ``nn.Module``\\ s,
:class:`FoldedIntegrator` and :class:`FoldedDecoder`, one frame being (Li et al. 2025,
Eq. 3, and the decode)::

    z_t = z_{t-1} + MLP_I([z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}])
    u = W_out [z_t; h_L] + b_out,  h_{i+1} = h_i + SiLU(W_i h_i + b_i),  x = u + x*_origin

PyTorch's deployment path is ``torch.export``: :func:`export_step` traces
:class:`FoldedStep` into an ``ExportedProgram`` (specialised to one frame's shapes and
dtypes), which ``torch.export.save`` writes and ``torch.export.load`` alone reads back;
``program.module()`` runs it.  :class:`ExportedStepper` steps with such programs,
:class:`TorchStepper` wraps any pair of PyTorch frame functions behind the
:class:`latentsim.runtime.Stepper` interface (tensors of one frame in and out); the eager
training modules are one (:class:`latentsim.latent.timing.EagerStepper`).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from latentsim.runtime.numpy_stepper import HARD_MODES

__all__ = ["ExportedStepper", "FoldedDecoder", "FoldedIntegrator", "FoldedStep", "TorchStepper", "export_step"]


def _linear(W, b, dtype: torch.dtype) -> nn.Linear:
    """An inference-only ``nn.Linear`` holding the folded float64 (W, b) in ``dtype``."""
    lin = nn.Linear(W.shape[1], W.shape[0], dtype=torch.float64)
    with torch.no_grad():
        lin.weight.copy_(torch.as_tensor(W))
        lin.bias.copy_(torch.as_tensor(b))
    return lin.to(dtype).requires_grad_(False)


class FoldedIntegrator(nn.Module):
    """z_t (r,) = z_{t-1} + MLP([z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}]) (without z_{t-1} if not residual)."""

    def __init__(self, folded: dict, dtype: torch.dtype = torch.float32):
        super().__init__()
        hdr = folded["header"]
        self.layers = nn.ModuleList([_linear(folded[f"int_W{i}"], folded[f"int_b{i}"], dtype) for i in range(int(hdr["integrator_layers"]))])
        self.residual = bool(hdr["residual"])

    def forward(self, z_prev, z_prev2, p, p_prev, p_prev2) -> torch.Tensor:
        h = torch.cat([z_prev, z_prev2, p, p_prev, p_prev2], -1)
        last = len(self.layers) - 1
        for i, lin in enumerate(self.layers):
            h = lin(h)
            if i < last:
                h = F.silu(h)
        return z_prev + h if self.residual else h


class FoldedDecoder(nn.Module):
    """Positions x (n, 3) float64 of latent z (r,) with Dirichlet positions xD (m, 3) float64."""

    def __init__(self, folded: dict, dtype: torch.dtype = torch.float32):
        super().__init__()
        hdr = folded["header"]
        self.skips = [bool(s) for s in hdr["decoder_skips"]]
        self.layers = nn.ModuleList([_linear(folded[f"dec_W{i}"], folded[f"dec_b{i}"], dtype) for i in range(len(self.skips))])
        self.mid = _linear(folded["dec_Wmid"], folded["dec_bmid"], dtype) if hdr.get("decoder_mid", False) else None
        self.out = _linear(folded["dec_Wout"], folded["dec_bout"], dtype)
        self.mode, self.n = str(hdr["mode"]), int(hdr["n_vertices"])
        # only the index lists this mode reads (torch.export.save cannot write empty tensors, e.g. root_slot of mean)
        for name in {"roots": ("dirichlet", "free", "root_slot"), "hard_mean": ("dirichlet", "free")}.get(self.mode, ()):
            self.register_buffer(name, torch.as_tensor(np.asarray(folded[name], dtype=np.int64)))

    def forward(self, z, xD) -> torch.Tensor:
        h = z
        for lin, skip in zip(self.layers, self.skips):
            y = F.silu(lin(h))
            h = h + y if skip else y
        if self.skips:
            h = torch.cat([z, h], -1)
        if self.mid is not None:
            h = self.mid(h)
        u = self.out(h).to(torch.float64).reshape(-1, 3)
        if self.mode in HARD_MODES:
            origin = xD.index_select(0, self.root_slot) if self.mode == "roots" else xD.mean(0, keepdim=True)
            x = torch.empty((self.n, 3), dtype=torch.float64, device=u.device)
            x.index_copy_(0, self.free, u + origin)
            x.index_copy_(0, self.dirichlet, xD)
            return x
        if xD.shape[0] > 0:
            return u + xD.mean(0)
        return u


class FoldedStep(nn.Module):
    """One frame: ``(z_{t-1}, z_{t-2} (r,), p_t, p_{t-1}, p_{t-2} (k,), xD (m, 3)) -> (z_t (r,), x_t (n, 3) float64)``."""

    def __init__(self, folded: dict, dtype: torch.dtype = torch.float32):
        super().__init__()
        self.integrator = FoldedIntegrator(folded, dtype)
        self.decoder = FoldedDecoder(folded, dtype)

    def forward(self, z_prev, z_prev2, p, p_prev, p_prev2, xD):
        z = self.integrator(z_prev, z_prev2, p, p_prev, p_prev2)
        return z, self.decoder(z, xD)


def _example_frame(folded: dict, dtype: torch.dtype) -> tuple:
    """Six distinct tensors of one frame's shapes (distinct: ``torch.export`` would treat one tensor passed twice as aliased)."""
    hdr = folded["header"]
    r, k, m = int(hdr["latent_dim"]), int(hdr["bc_dim"]), len(folded["dirichlet"])
    return tuple(torch.zeros(s, dtype=dtype) for s in (r, r, k, k, k)) + (torch.zeros((m, 3), dtype=torch.float64),)


def export_step(folded: dict, dtype: torch.dtype = torch.float32, part: str = "step") -> torch.export.ExportedProgram:
    """The folded step (or its ``part`` ``"integrate"`` or ``"decode"``) as a ``torch.export`` program.

    Specialised to the runtime's shapes: z (r,), p (k,) in ``dtype``, xD (m, 3) float64.
    ``torch.export.save(program, path)`` writes it; ``torch.export.load(path).module()`` runs it.
    """
    args = _example_frame(folded, dtype)
    step = FoldedStep(folded, dtype).eval()
    module, args = {"step": (step, args), "integrate": (step.integrator, args[:5]), "decode": (step.decoder, (args[0], args[5]))}[part]
    with torch.no_grad():
        return torch.export.export(module, args)


class TorchStepper:
    """A stepper over PyTorch callables (a :class:`latentsim.runtime.Stepper`; tensors of one frame).

    Parameters
    ----------
    integrate : ``(z_prev, z_prev2, p, p_prev, p_prev2) -> z`` (r,).
    decode : ``(z, xD) -> x`` (n, 3) float64.
    step : ``(z_prev, z_prev2, p, p_prev, p_prev2, xD) -> (z, x)``; default: integrate, then decode.
    r, k, n : latent dimension, parameters per frame, vertices.
    dtype : the network's dtype (a torch dtype).

    Runs under ``torch.inference_mode``; returns new tensors (copied into ``out=`` where given).
    """

    def __init__(self, integrate, decode, r: int, k: int, n: int, dtype: torch.dtype = torch.float32, step=None):
        self._integrate, self._decode, self._step = integrate, decode, step
        self.r, self.k, self.n = int(r), int(k), int(n)
        self.torch_dtype = dtype
        self.dtype = np.dtype(torch.empty(0, dtype=dtype).numpy().dtype)

    def inputs(self, z_prev, z_prev2, p, p_prev, p_prev2, xD) -> tuple:
        """New tensors of one frame's arguments: latents and parameters in the network dtype, xD float64."""
        net = tuple(torch.tensor(np.asarray(a), dtype=self.torch_dtype) for a in (z_prev, z_prev2, p, p_prev, p_prev2))
        return net + (torch.tensor(np.asarray(xD), dtype=torch.float64),)

    def integrate(self, z_prev, z_prev2, p, p_prev, p_prev2, out=None):
        with torch.inference_mode():
            z = self._integrate(z_prev, z_prev2, p, p_prev, p_prev2)
        if out is not None:
            out[...] = z
            return out
        return z

    def decode(self, z, xD, out=None):
        with torch.inference_mode():
            x = self._decode(z, xD)
        if out is not None:
            out[...] = x
            return out
        return x

    def step(self, z_prev, z_prev2, p, p_prev, p_prev2, xD, z_out=None, x_out=None):
        if self._step is None:
            z = self.integrate(z_prev, z_prev2, p, p_prev, p_prev2, out=z_out)
            return z, self.decode(z, xD, out=x_out)
        with torch.inference_mode():
            z, x = self._step(z_prev, z_prev2, p, p_prev, p_prev2, xD)
        if z_out is not None:
            z_out[...] = z
            z = z_out
        if x_out is not None:
            x_out[...] = x
            x = x_out
        return z, x


class ExportedStepper(TorchStepper):
    """The folded step run as ``torch.export`` programs (:func:`export_step`: the step, and its integrate and
    decode halves, each ``program.module()``): PyTorch's deployment path."""

    def __init__(self, folded: dict, dtype: torch.dtype = torch.float32):
        hdr = folded["header"]
        parts = {part: export_step(folded, dtype, part).module() for part in ("integrate", "decode", "step")}
        super().__init__(parts["integrate"], parts["decode"], hdr["latent_dim"], hdr["bc_dim"], hdr["n_vertices"], dtype, step=parts["step"])

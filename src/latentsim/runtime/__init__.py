"""Deployable latent runtime: step a frame of Li et al. 2025 without the training code.

A trained latent integrator and decoder are folded into a handful of dense layers
(:mod:`latentsim.runtime.fold`: BatchNorm, input standardisation and output scaling,
the PCA skip path), one frame being (paper Eq. 3 and the decode)::

    z_t = z_{t-1} + MLP_I([z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}])
    h_0 = z_t,  h_{i+1} = h_i + SiLU(W_i h_i + b_i),   u = W_cat [z_t; h_L] + b_cat,   x = decode_relative(u, x*_D)

Every runtime is a :class:`Stepper` (:mod:`latentsim.runtime.stepper`) over the same folded arrays:

- :class:`NumpyStepper` (:mod:`~latentsim.runtime.numpy_stepper`): plain NumPy, preallocated
  buffers, float32 or float64 networks; also the forward-mode derivatives of the decode;
- :class:`latentsim.runtime.compiled.CompiledStepper`: the same frame as one numba kernel call;
- :class:`ExportedStepper` (:mod:`~latentsim.runtime.torch_stepper`): the folded step as
  ``torch.export`` programs, PyTorch's deployment path.  The runtime knows no training module:
  the eager baseline that steps them, :class:`latentsim.latent.timing.EagerStepper`, lives with them.

Files (:mod:`~latentsim.runtime.files`): ``runtime.npz`` (NumPy, no pickle) and a
``torch.export`` program (``.pt2``); timing in :mod:`~latentsim.runtime.timing`.
"""

from latentsim.runtime.files import export_runtime, load_runtime, read_runtime
from latentsim.runtime.encoder import Encoder
from latentsim.runtime.fold import FORMAT, VERSION, fold_decoder, fold_encoder, fold_networks
from latentsim.runtime.model import TrainedModel, load
from latentsim.runtime.numpy_stepper import NumpyStepper
from latentsim.runtime.stepper import Stepper, rollout_runtime
from latentsim.runtime.timing import jvp_vertex_torch, time_jvp, time_step
from latentsim.runtime.torch_stepper import ExportedStepper, FoldedStep, TorchStepper, export_step


__all__ = [
    "FORMAT",
    "VERSION",
    "Encoder",
    "ExportedStepper",
    "FoldedStep",
    "NumpyStepper",
    "Stepper",
    "TorchStepper",
    "TrainedModel",
    "export_runtime",
    "export_step",
    "fold_decoder",
    "fold_encoder",
    "fold_networks",
    "jvp_vertex_torch",
    "load",
    "load_runtime",
    "read_runtime",
    "rollout_runtime",
    "time_jvp",
    "time_step",
]

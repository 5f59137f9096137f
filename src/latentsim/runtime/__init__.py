"""Deployable latent runtime: encode and step a trained model of Li et al. 2025 without the training code.

A user's entry point is :func:`load` (:mod:`~latentsim.runtime.model`): the rollout stage leaves each
trained model as ``results/rollout/{scene}/{method}/seed{k}/runtime.npz`` (one per seed), and::

    from latentsim import runtime
    model = runtime.load("results/rollout/tiny_rods/self_supervised/seed0")   # a TrainedModel
    model.encode(x0, x1, xD[:2], p[:2])     # two frames' positions (n, 3), Dirichlet positions, parameters (2, k)
    x2 = model.step(p[2], xD[2])            # the next frame's positions (n, 3), float64
    x3 = model.step(p[3], xD[3])            # ...

(``examples/step_trained_model.py`` does this on a test sequence.)  A trained encoder, latent
integrator and decoder are folded into a handful of dense layers (:mod:`latentsim.runtime.fold`:
BatchNorm, input standardisation and output scaling, the PCA skip paths), one frame being (paper
Eq. 3 and the decode)::

    z_t = z_{t-1} + MLP_I([z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}])
    h_0 = z_t,  h_{i+1} = h_i + SiLU(W_i h_i + b_i),   u = W_cat [z_t; h_L] + b_cat,   x = decode_relative(u, x*_D)

and the encoder (:mod:`~latentsim.runtime.encoder`) giving the latents of the first two frames as the
pipeline does (relative coordinates in float64, then the network).

Every runtime is a :class:`Stepper` (:mod:`latentsim.runtime.stepper`) over the same folded arrays,
``step(z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}, xD_t) -> (z_t, x_t)``; :class:`TrainedModel` keeps that state:

- :class:`NumpyStepper` (:mod:`~latentsim.runtime.numpy_stepper`): plain NumPy, preallocated
  buffers, float32 or float64 networks; also the encoder (``encode``) and the forward-mode
  derivatives of the decode;
- :class:`latentsim.runtime.compiled.CompiledStepper`: the same frame as one numba kernel call;
- :class:`ExportedStepper` (:mod:`~latentsim.runtime.torch_stepper`): the folded step as
  ``torch.export`` programs, PyTorch's deployment path (the step only: a rollout starts from latents
  that the NumPy encoder gives).  The runtime knows no training module: the eager baseline that
  steps them, :class:`latentsim.latent.timing.EagerStepper`, lives with them.
- :class:`RigidFrameStepper` (:mod:`~latentsim.runtime.frame`): any of them, for a model whose
  autoencoder encodes positions in the frame that turns with the prescribed vertices
  (``autoencoder.rigid_frame``): it decodes in the frame and carries the positions out
  (:class:`TrainedModel` puts it on by itself, from the file's header).

Files (:mod:`~latentsim.runtime.files`): ``runtime.npz`` (NumPy, no pickle; format version 2 holds the
encoder, version 1 files step but cannot encode) and a ``torch.export`` program of the step
(``runtime.pt``); timing in :mod:`~latentsim.runtime.timing`.  See ``docs/artefacts.md``.
"""

from latentsim.runtime.encoder import Encoder
from latentsim.runtime.files import export_runtime, load_program, load_runtime, read_runtime
from latentsim.runtime.frame import RigidFrameStepper
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
    "RigidFrameStepper",
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
    "load_program",
    "load_runtime",
    "read_runtime",
    "rollout_runtime",
    "time_jvp",
    "time_step",
]

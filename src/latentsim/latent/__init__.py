"""Latent-space dynamics: the learning core of Li et al. 2025, "Self-supervised Learning of
Latent Space Dynamics" (sections 3.2-3.3).

1. :mod:`~latentsim.latent.coordinates` - :class:`RelativeCoordinates`, positions expressed
   relative to the Dirichlet boundary conditions (root-relative for rods, relative to the mean
   Dirichlet position for cloth and solids), the vector the autoencoder sees.
2. :mod:`~latentsim.latent.autoencoder` - :class:`Autoencoder`, a symmetric MLP ResNet
   (BatchNorm + SiLU/Swish) whose outer linear layers are initialised from PCA (Fulton et al.
   2019), and its training :func:`fit_autoencoder` (Eq. 2).
3. :mod:`~latentsim.latent.integrator` - :class:`LatentIntegrator`, an MLP (SiLU) mapping
   ``[z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}]`` to ``z_t`` (Eq. 3).
4. :mod:`~latentsim.latent.loss` - :func:`integrator_loss`, the incremental potential of the
   decoded prediction (Eq. 4) with training noise (Eq. 5) and data balancing (Eq. 6); or the
   supervised L2 baseline.
5. :mod:`~latentsim.latent.data` (sequences, triplets; as records, :mod:`~latentsim.latent.batch`),
   :mod:`~latentsim.latent.training` (:func:`fit_integrator`, with checkpoint/resume; the features
   beyond the paper as pieces, :mod:`~latentsim.latent.features`), :mod:`~latentsim.latent.serialization`
   (save/load), :mod:`~latentsim.latent.rollout` (autoregressive inference with divergence
   detection).

Beside them: :mod:`~latentsim.latent.timing` (same-run timings), :mod:`~latentsim.latent.stability`
(stress conditions) and :mod:`~latentsim.latent.subspaces` (the PCA, linear-modes and autoencoder subspaces of the
reduced baselines, whose stage is :mod:`~latentsim.stages.baselines`), imported by name; the sizing sweep, which
trains and measures whole models, is a stage (:mod:`~latentsim.stages.sweep`).

Physics is never re-implemented here: every energy comes from an
:class:`latentsim.physics.incremental_potential.IncrementalPotential`.  Networks run in
float32; decoded states are cast to float64 before the potential is evaluated.  Settings come
from the config schema (``workflow/schemas/config.schema.yaml``), the one table of defaults.
"""

from latentsim.latent.autoencoder import Autoencoder, decode_latents, encode_positions, fit_autoencoder, pca_basis, reconstruction_mse
from latentsim.latent.base import TrainingDiverged, resolve_device
from latentsim.latent.coordinates import RelativeCoordinates, coordinates_for
from latentsim.latent.data import BATCH_KEYS, build_triplets, load_sequences
from latentsim.latent.integrator import LatentIntegrator
from latentsim.latent.loss import balancing_weights, fixed_balancing_weights, integrator_loss
from latentsim.latent.rollout import rollout
from latentsim.latent.serialization import autoencoder_coordinates, load_autoencoder, load_extra, load_integrator, save_module
from latentsim.latent.training import fit_integrator, training_fingerprint

__all__ = [
    "BATCH_KEYS",
    "Autoencoder",
    "LatentIntegrator",
    "RelativeCoordinates",
    "TrainingDiverged",
    "autoencoder_coordinates",
    "balancing_weights",
    "build_triplets",
    "coordinates_for",
    "decode_latents",
    "encode_positions",
    "fit_autoencoder",
    "fit_integrator",
    "integrator_loss",
    "load_autoencoder",
    "load_extra",
    "load_integrator",
    "load_sequences",
    "pca_basis",
    "reconstruction_mse",
    "resolve_device",
    "rollout",
    "save_module",
    "training_fingerprint",
]

"""Stage of rule ``train_integrator`` (workflow/rules/integrator.smk): the latent integrator of
Li et al. 2025 (sec. 3.3; self-supervised, Eqs. 4-6, or a supervised variant) fitted on a
scene's training sequences through its trained autoencoder, with a checkpoint that a killed
training resumes from.
"""

from __future__ import annotations

import logging
import os
from dataclasses import replace

import numpy as np

from latentsim.config import with_defaults
from latentsim.io import atomic_h5, open_artefact, write_dataset
from latentsim.latent.conditioning import Conditioning
from latentsim.latent.data import load_split
from latentsim.latent.serialization import autoencoder_coordinates, load_autoencoder, save_module
from latentsim.latent.training import fit_integrator
from latentsim.scene import potential_from_artefact

log = logging.getLogger(__name__)


def train_integrator(trajectories, ae_path, settings: dict, seed: int, device: str, out_model, out_history, checkpoint=None, progress=False, label="",
                     conditioning: dict | None = None):  # fmt: skip
    """Fit the latent integrator (self-supervised or supervised) on the training sequences.

    ``settings``: the method's ``integrator`` block (keys absent take the schema's defaults), which
    ``out_history`` records as its config.  ``label`` names the training in messages (scene and
    method).  The recorded ``train_seconds`` is the training's whole time, a killed run's part up
    to its checkpoint included.  A training that diverges raises
    :class:`~latentsim.latent.base.TrainingDiverged` and writes neither output (the checkpoint
    keeps the last good epoch).

    ``trajectories``: a scene's ``trajectories.h5``, or a list of several of one mesh (a conditioned
    scene's training conditions).  ``conditioning``: None, or the box to train over, ``{time_step:
    [lo, hi], youngs_modulus: [lo, hi]}`` and optionally the loss weight's ``time_step_weight_power``
    (:mod:`latentsim.latent.conditioning`; the first file's
    time step and modulus are the potential's own); the model file records it.
    """
    cfg = with_defaults("integrator", settings, "train_integrator")
    paths = [trajectories] if isinstance(trajectories, (str, os.PathLike)) else list(trajectories)
    with open_artefact(paths[0]) as f:
        coords = autoencoder_coordinates(f, ae_path)
        potential = potential_from_artefact(f)
        box = None
        if conditioning is not None:
            box = Conditioning(tuple(conditioning["time_step"]), tuple(conditioning["youngs_modulus"]), float(f.attrs["dt"]), float(f.attrs["youngs_modulus"]))
            if "time_step_weight_power" in conditioning:  # absent: the schema's default
                box = replace(box, time_step_weight_power=float(conditioning["time_step_weight_power"]))
    train = load_split(paths, "train")
    ae = load_autoencoder(ae_path)
    integ, history = fit_integrator(
        ae, coords, potential, list(train.values()), cfg, seed=seed, device=device, progress=progress, checkpoint_path=checkpoint, label=label,
        conditioning=box,
    )  # fmt: skip
    seconds = history["train_seconds"]
    log.info("integrator (%s): %d triplets, %.1f s, final loss %.4e", cfg["mode"], history["n_triplets"], seconds, history["loss"][-1])
    extra = {"mode": cfg["mode"], "train_seconds": seconds}
    if box is not None:
        extra["conditioning"] = box.to_dict()
    save_module(out_model, integ.cpu(), extra=extra)
    with atomic_h5(out_history, config=settings, seed=seed) as g:
        g.attrs["train_seconds"] = seconds
        g.attrs["start_epoch"] = int(history["start_epoch"])
        write_dataset(g, "loss", np.asarray(history["loss"], dtype=np.float64))
        write_dataset(g, "latent_mse", np.asarray(history["latent_mse"], dtype=np.float64))
        if "own_triplets" in history:  # the rows of each own rollout: fewer where they stop inside a collider
            write_dataset(g, "own_triplets", np.asarray(history["own_triplets"], dtype=np.int64))
    # the checkpoint serves a killed training only: left behind, a forced rerun of the same training would
    # resume at its last epoch and record a training time of a second
    if checkpoint is not None and os.path.exists(checkpoint):
        os.remove(checkpoint)

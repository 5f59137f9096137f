"""Stage of rule ``train_autoencoder`` (workflow/rules/autoencoder.smk): the autoencoder of
Li et al. 2025 (sec. 3.2) fitted on every training frame of a scene's ``trajectories.h5``, and
every sequence encoded with its reconstruction error.
"""

from __future__ import annotations

import logging
import os
import time

import numpy as np
import torch

from latentsim.config import with_defaults
from latentsim.io import atomic_h5, open_artefact, write_dataset
from latentsim.latent.autoencoder import LatentRankError, decode_latents, encode_positions, fit_autoencoder
from latentsim.latent.coordinates import coordinates_for, coordinates_record
from latentsim.latent.data import load_split
from latentsim.latent.serialization import save_module
from latentsim.report.metrics import bbox_diagonal, penetration
from latentsim.scene import contact_from_artefact

log = logging.getLogger(__name__)


def reconstruction_errors(ae, coords, seq: dict, diag: float, contact=None) -> tuple[dict, torch.Tensor]:
    """Of encode-decode over a sequence: ``mean_error`` and ``max_error`` (vertex error / bbox diagonal)
    and, with the scene's ``contact``, how deep the reconstruction enters its colliders
    (:func:`~latentsim.report.metrics.penetration`: ``max_penetration``, ``penetrating_frames``; the ground
    truth never enters, so this is what the decoder adds, a floor under every method that decodes through
    it); and the sequence's latents."""
    x = torch.as_tensor(seq["positions"])
    xD = torch.as_tensor(seq["dirichlet_positions"])
    with torch.no_grad():
        z = encode_positions(ae, coords, x, xD)
        xr = decode_latents(ae, coords, z, xD).cpu().numpy()
    d = np.linalg.norm(xr - seq["positions"], axis=-1) / diag
    out = {"mean_error": float(d.mean()), "max_error": float(d.max())}
    if contact is not None:
        out.update(penetration(contact, xr, diag, -1, seq["dirichlet_positions"]))
    return out, z


def train_autoencoder(trajectories, settings: dict, seed: int, device: str, out_model, out_latents, progress=False, label=""):
    """Fit the autoencoder on every training frame; encode every sequence.

    ``trajectories``: a scene's ``trajectories.h5``, or a list of several of one mesh (a conditioned
    scene's conditions; :func:`~latentsim.latent.data.load_split` names their sequences).

    ``settings``: the scene's ``autoencoder`` block (keys absent take the schema's defaults), which
    ``out_latents`` records as its config.  ``label`` names the training in messages (the scene,
    and the method of a variant's own autoencoder).  A training that diverges raises
    :class:`~latentsim.latent.base.TrainingDiverged` and writes neither output.
    """
    cfg = with_defaults("autoencoder", settings, "train_autoencoder")
    paths = [trajectories] if isinstance(trajectories, (str, os.PathLike)) else list(trajectories)
    with open_artefact(paths[0]) as f:
        coords = coordinates_for(f, cfg["coordinates"], cfg["rigid_frame"])
        diag = bbox_diagonal(f["rest_positions"][()])
        scene = f.attrs.get("scene", "?")
        contact = contact_from_artefact(f)
    train, every = load_split(paths, "train"), load_split(paths)
    U = torch.cat([coords.encode(torch.as_tensor(s["positions"]), torch.as_tensor(s["dirichlet_positions"])) for s in train.values()])
    t0 = time.perf_counter()
    try:
        ae, history = fit_autoencoder(U.to(torch.float32), cfg, seed=seed, device=device, progress=progress, label=label)
    except LatentRankError as e:
        raise LatentRankError(f"scene {scene} ({trajectories}, training sequences {sorted(train)}): {e}") from None
    seconds = time.perf_counter() - t0
    ae = ae.cpu()
    log.info(
        "autoencoder: %d frames of %d dims -> %d latents, %.1f s, mse %.3e (PCA start) -> %.3e (kept: %s)",
        U.shape[0], U.shape[1], cfg["latent_dim"], seconds, history["mse_initial"], history["mse_final"], history["kept"],
    )  # fmt: skip
    save_module(out_model, ae, extra={**coordinates_record(coords), "train_seconds": seconds})
    with atomic_h5(out_latents, config=settings, seed=seed) as g:
        g.attrs["train_seconds"] = seconds
        g.attrs["kept"] = history["kept"]
        write_dataset(g, "loss", np.asarray(history["loss"], dtype=np.float64))
        grp = g.create_group("sequences", track_order=True)
        for name, s in every.items():
            errors, z = reconstruction_errors(ae, coords, s, diag, contact)
            h = grp.create_group(name)
            h.attrs["split"] = s["split"]
            h.attrs.update(errors)
            write_dataset(h, "latents", z.numpy())
            log.info("reconstruction %s (%s): mean %.3e, max %.3e of the bbox diagonal%s", name, s["split"], errors["mean_error"], errors["max_error"],
                     f"; {100 * errors['max_penetration']:.2f}% of it inside a collider at the deepest" if contact is not None else "")  # fmt: skip

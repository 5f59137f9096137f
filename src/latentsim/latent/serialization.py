"""Saving and loading the trained networks of the latent method (autoencoder and latent
integrator), each file ``{"kind", "hparams", "state_dict", "extra"}`` written atomically
(temp file + ``os.replace``) and read with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import os

import torch
from torch import nn

from latentsim.latent.autoencoder import Autoencoder
from latentsim.latent.base import resolve_device
from latentsim.latent.coordinates import RelativeCoordinates, coordinates_for
from latentsim.latent.integrator import LatentIntegrator


def save_module(path: str | os.PathLike, module: nn.Module, extra: dict | None = None) -> None:
    """Atomically save ``{"hparams", "state_dict", "extra"}`` (temp file + os.replace)."""
    blob = {"kind": type(module).__name__, "hparams": module.hparams, "state_dict": module.state_dict(), "extra": extra or {}}
    atomic_save(blob, path)


def atomic_save(obj, path) -> None:
    """``torch.save`` to a temporary file beside ``path``, then ``os.replace`` it there."""
    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".tmp"
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _load_blob(path, kind):
    blob = torch.load(os.fspath(path), map_location="cpu", weights_only=True)
    if blob.get("kind") != kind:
        raise ValueError(f"{path}: holds a {blob.get('kind')!r}, expected {kind!r}")
    return blob


def load_autoencoder(path, device="cpu") -> Autoencoder:
    """Load an autoencoder written by :func:`save_module` (eval mode)."""
    blob = _load_blob(path, "Autoencoder")
    h = blob["hparams"]
    model = Autoencoder(h["input_dim"], h["latent_dim"], h["widths"], h["pca_dim"])
    model.load_state_dict(blob["state_dict"])
    return model.to(resolve_device(device)).eval()


def load_integrator(path, device="cpu") -> LatentIntegrator:
    """Load an integrator written by :func:`save_module` (eval mode)."""
    blob = _load_blob(path, "LatentIntegrator")
    h = blob["hparams"]
    model = LatentIntegrator(h["latent_dim"], h["bc_dim"], h["widths"], h["residual"])
    model.load_state_dict(blob["state_dict"])
    return model.to(resolve_device(device)).eval()


def load_extra(path) -> dict:
    """The ``extra`` dict a file written by :func:`save_module` records (mode, coordinates,
    training time, ...)."""
    return torch.load(os.fspath(path), map_location="cpu", weights_only=True).get("extra", {})


def autoencoder_coordinates(f, ae_path) -> RelativeCoordinates:
    """The coordinates the autoencoder saved at ``ae_path`` was trained in (its file records
    them), for the scene of the open trajectories file ``f``."""
    return coordinates_for(f, load_extra(ae_path).get("coordinates"))

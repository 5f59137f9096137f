"""Saving and loading the trained networks of the latent method (autoencoder and latent
integrator), each file ``{"kind", "hparams", "state_dict", "extra", "environment", "sha256"}`` written atomically
(temp file + ``os.replace``) and read, checked, with :func:`load_checked`: every PyTorch file of
the pipeline (the Neural Modes networks and training checkpoints too) stores the checksum of its
dict (:func:`torch_checksum`) under ``sha256`` and is loaded only through it, and the processor and
libraries that computed it (:func:`latentsim.provenance.environment`) under ``environment``, which the
loaders of networks and checkpoints do not read.
"""

from __future__ import annotations

import os

import torch
from torch import nn

from latentsim.checksum import KEY, Digest, corrupt, unverified
from latentsim.latent.autoencoder import Autoencoder
from latentsim.latent.base import resolve_device
from latentsim.latent.coordinates import RelativeCoordinates, coordinates_for
from latentsim.latent.integrator import LatentIntegrator
from latentsim.provenance import ENVIRONMENT, environment


def save_module(path: str | os.PathLike, module: nn.Module, extra: dict | None = None) -> None:
    """Atomically save ``{"hparams", "state_dict", "extra"}`` (temp file + os.replace)."""
    blob = {"kind": type(module).__name__, "hparams": module.hparams, "state_dict": module.state_dict(), "extra": extra or {}}
    atomic_save(blob, path)


def atomic_save(obj: dict, path) -> None:
    """``torch.save`` the dict ``obj`` with the computing environment (under ``environment``) and
    the checksum of both (:func:`torch_checksum`, under ``sha256``) to a temporary file beside
    ``path``, then ``os.replace`` it there."""
    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".tmp"
    obj = {**obj, ENVIRONMENT: environment()}
    torch.save({**obj, KEY: torch_checksum(obj)}, tmp)
    os.replace(tmp, path)


def torch_checksum(obj: dict) -> str:
    """SHA-256 (hex) of a dict of tensors and settings, nested: each tensor's key path, dtype,
    shape and bytes, each other value's ``repr``, in the dict's order (a top-level ``sha256`` left out)."""
    d = Digest()

    def visit(name: str, v) -> None:
        if isinstance(v, dict):
            d.value(name, ("dict", len(v)))
            for k, item in v.items():
                if not (name == "" and k == KEY):
                    visit(f"{name}/{k!r}", item)
        elif isinstance(v, (list, tuple)) and any(torch.is_tensor(x) or isinstance(x, dict) for x in v):
            d.value(name, (type(v).__name__, len(v)))
            for i, item in enumerate(v):
                visit(f"{name}/{i}", item)
        elif torch.is_tensor(v):
            t = v.detach().cpu().contiguous().reshape(-1)
            d.value(name, ("tensor", str(v.dtype), tuple(v.shape)))
            d.array(name, t.view(torch.uint8).numpy())
        else:
            d.value(name, v)

    visit("", obj)
    return d.hexdigest()


def load_checked(path) -> dict:
    """The dict a file written by :func:`atomic_save` holds, its checksum verified (``sha256``
    removed).  A file without one (written before checksums) is read with a warning.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    ArtefactError
        The file is truncated, unreadable or does not match its checksum: it has been moved aside
        to ``<path>.corrupt`` and the message, naming it, says to run snakemake again.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # truncated or damaged zip: OSError, RuntimeError, EOFError, UnpicklingError, ...
        raise corrupt(path, f"PyTorch cannot load it: {type(err).__name__}: {err}") from err
    if not isinstance(blob, dict):
        raise corrupt(path, f"holds a {type(blob).__name__}, not a dict")
    stored = blob.pop(KEY, None)
    if stored is None:
        unverified(path)
    elif (actual := torch_checksum(blob)) != stored:
        raise corrupt(path, f"its content does not match its checksum (sha256 {actual[:12]}..., recorded {str(stored)[:12]}...)")
    return blob


def load_blob(path, kind: str) -> dict:
    """A network file written by :func:`save_module` (:func:`load_checked`) holding a ``kind``."""
    blob = load_checked(path)
    if blob.get("kind") != kind:
        raise ValueError(f"{path}: holds a {blob.get('kind')!r}, expected {kind!r}")
    return blob


def load_autoencoder(path, device="cpu") -> Autoencoder:
    """Load an autoencoder written by :func:`save_module` (eval mode)."""
    blob = load_blob(path, "Autoencoder")
    h = blob["hparams"]
    model = Autoencoder(h["input_dim"], h["latent_dim"], h["widths"], h["pca_dim"])
    model.load_state_dict(blob["state_dict"])
    return model.to(resolve_device(device)).eval()


def load_integrator(path, device="cpu") -> LatentIntegrator:
    """Load an integrator written by :func:`save_module` (eval mode)."""
    blob = load_blob(path, "LatentIntegrator")
    h = blob["hparams"]
    model = LatentIntegrator(h["latent_dim"], h["bc_dim"], h["widths"], h["residual"], origin=bool(h.get("origin", False)))
    model.load_state_dict(blob["state_dict"])
    return model.to(resolve_device(device)).eval()


def load_extra(path) -> dict:
    """The ``extra`` dict a file written by :func:`save_module` records (mode, coordinates,
    training time, ...)."""
    return load_checked(path).get("extra", {})


def autoencoder_coordinates(f, ae_path) -> RelativeCoordinates:
    """The coordinates the autoencoder saved at ``ae_path`` was trained in (its file records
    them), for the scene of the open trajectories file ``f``."""
    extra = load_extra(ae_path)
    return coordinates_for(f, extra.get("coordinates"), bool(extra.get("rigid_frame", False)))

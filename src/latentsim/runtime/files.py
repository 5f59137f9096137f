"""The deployable runtime's files: ``runtime.npz`` (NumPy) and a ``torch.export`` program.

- ``*.npz``: the folded float64 weights and index arrays of :func:`latentsim.runtime.fold_networks`
  (the encoder's too, from format version 2; version 1 files are read, and step, but cannot encode)
  plus a JSON ``header`` (its ``format`` and ``version`` checked on reading); NumPy only,
  ``allow_pickle=False``.  :func:`load_runtime` steps it with a
  :class:`latentsim.runtime.NumpyStepper` (:func:`latentsim.runtime.compiled.load_runtime`:
  the compiled stepper).
- ``*.pt2`` (``*.pt`` accepted too): the folded step as a ``torch.export`` program in the
  network dtype (:func:`latentsim.runtime.torch_stepper.export_step`), written with
  ``torch.export.save``; ``torch.export.load(path).module()`` alone runs it.

Both are written under a temporary name and renamed.  See ``docs/artefacts.md``.
"""

from __future__ import annotations

import json
import os

import numpy as np
import torch

from latentsim.runtime.fold import FORMAT, VERSION, fold_networks
from latentsim.runtime.numpy_stepper import NumpyStepper
from latentsim.runtime.torch_stepper import export_step

__all__ = ["EXPORT_SUFFIXES", "export_runtime", "load_runtime", "read_runtime"]

EXPORT_SUFFIXES = (".pt2", ".pt")  # a torch.export program (.pt2 is torch.export's own suffix)


def export_runtime(ae, integrator, coords, path, dtype: torch.dtype = torch.float32) -> dict:
    """Write the deployable runtime of a trained integrator + decoder; returns the folded dict.

    ``path`` ending in ``.npz``: the folded arrays (NumPy); in ``.pt2`` or ``.pt``: the
    ``torch.export`` program of the step in ``dtype``.
    """
    path = os.fspath(path)
    folded = fold_networks(ae, integrator, coords)
    os.makedirs(os.path.dirname(os.path.abspath(path)) or ".", exist_ok=True)
    if path.endswith(".npz"):
        tmp = path[:-4] + ".tmp.npz"
        arrays = {k: v for k, v in folded.items() if k != "header"}
        np.savez(tmp, header=np.asarray(json.dumps(folded["header"])), **arrays)
    elif path.endswith(EXPORT_SUFFIXES):
        tmp = path[: path.rindex(".")] + ".tmp.pt2"  # torch.export.save expects its own suffix
        torch.export.save(export_step(folded, dtype), tmp)
    else:
        raise ValueError(f"runtime path {path!r}: use a .npz (NumPy) or .pt2 (torch.export) file name")
    os.replace(tmp, path)
    return folded


def read_runtime(path) -> dict:
    """The folded dict (arrays and ``header``) of a ``runtime.npz`` file."""
    with np.load(os.fspath(path), allow_pickle=False) as f:
        folded = {k: f[k] for k in f.files if k != "header"}
        folded["header"] = json.loads(str(f["header"]))
    if folded["header"].get("format") != FORMAT:
        raise ValueError(f"{path}: not a latent runtime file")
    if int(folded["header"].get("version", -1)) > VERSION:
        raise ValueError(f"{path}: runtime format version {folded['header']['version']} is newer than {VERSION}")
    return folded


def load_runtime(path, dtype=np.float32) -> NumpyStepper:
    """The :class:`NumpyStepper` (network ``dtype``) of a ``runtime.npz`` file."""
    path = os.fspath(path)
    if path.endswith(EXPORT_SUFFIXES):
        raise ValueError(f"{path}: a torch.export program; torch.export.load(path).module() runs it")
    if not path.endswith(".npz"):
        raise ValueError(f"runtime path {path!r}: use a .npz file")
    return NumpyStepper(read_runtime(path), dtype=dtype, source=path)

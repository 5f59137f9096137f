"""The deployable runtime's files: ``runtime.npz`` (NumPy) and a ``torch.export`` program.

- ``*.npz``: the folded float64 weights and index arrays of :func:`latentsim.runtime.fold_networks`
  (the encoder's too, from format version 2; version 1 files are read, and step, but cannot encode)
  plus a JSON ``header`` (its ``format`` and ``version`` checked on reading), ``environment`` (JSON of
  the processor and libraries that wrote it, :func:`latentsim.provenance.environment`; not returned
  by the readers) and ``sha256``, the checksum of the others (:func:`npz_checksum`, verified on reading); NumPy only, ``allow_pickle=False``.  :func:`load_runtime` steps it with a
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

from latentsim.checksum import KEY, Digest, corrupt, unverified
from latentsim.provenance import ENVIRONMENT, environment
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
        arrays["header"] = np.asarray(json.dumps(folded["header"]))
        arrays[ENVIRONMENT] = np.asarray(json.dumps(environment(), sort_keys=True))
        np.savez(tmp, **arrays, **{KEY: np.asarray(npz_checksum(arrays))})
    elif path.endswith(EXPORT_SUFFIXES):
        tmp = path[: path.rindex(".")] + ".tmp.pt2"  # torch.export.save expects its own suffix
        torch.export.save(export_step(folded, dtype), tmp)
    else:
        raise ValueError(f"runtime path {path!r}: use a .npz (NumPy) or .pt2 (torch.export) file name")
    os.replace(tmp, path)
    return folded


def read_runtime(path) -> dict:
    """The folded dict (arrays and ``header``) of a ``runtime.npz`` file."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except Exception as err:  # truncated or damaged zip: BadZipFile (CRC), EOFError, ValueError, OSError, ...
        raise corrupt(path, f"NumPy cannot read it: {type(err).__name__}: {err}") from err
    stored = arrays.pop(KEY, None)
    if stored is None:
        unverified(path)
    elif (actual := npz_checksum(arrays)) != str(stored):
        raise corrupt(path, f"its content does not match its checksum (sha256 {actual[:12]}..., recorded {str(stored)[:12]}...)")
    if "header" not in arrays:
        raise ValueError(f"{path}: not a latent runtime file (no header)")
    folded = {k: v for k, v in arrays.items() if k not in ("header", ENVIRONMENT)}
    folded["header"] = json.loads(str(arrays["header"]))
    if folded["header"].get("format") != FORMAT:
        raise ValueError(f"{path}: not a latent runtime file")
    if int(folded["header"].get("version", -1)) > VERSION:
        raise ValueError(f"{path}: runtime format version {folded['header']['version']} is newer than {VERSION}")
    return folded


def npz_checksum(arrays: dict) -> str:
    """SHA-256 (hex) of a runtime file's arrays (the ``header`` and ``environment`` strings among them): each array's
    name, dtype, shape and bytes, in sorted order."""
    d = Digest()
    for k in sorted(arrays):
        d.array(k, arrays[k])
    return d.hexdigest()


def load_runtime(path, dtype=np.float32) -> NumpyStepper:
    """The :class:`NumpyStepper` (network ``dtype``) of a ``runtime.npz`` file."""
    path = os.fspath(path)
    if path.endswith(EXPORT_SUFFIXES):
        raise ValueError(f"{path}: a torch.export program; torch.export.load(path).module() runs it")
    if not path.endswith(".npz"):
        raise ValueError(f"runtime path {path!r}: use a .npz file")
    return NumpyStepper(read_runtime(path), dtype=dtype, source=path)

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
  ``torch.export.save``, with the checksum of its weights and constants (:func:`program_checksum`) and the
  ``environment`` as extra files; :func:`load_program` checks it and runs it on inputs of any float dtype
  (``torch.export.load(path).module()`` alone runs it too, unchecked, on inputs of its own dtypes).

Both are written under a temporary name and renamed; a write that fails leaves no temporary file behind.
See ``docs/artefacts.md``.
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

__all__ = ["EXPORT_SUFFIXES", "export_runtime", "load_program", "load_runtime", "program_checksum", "read_runtime"]

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
        write = lambda: np.savez(tmp, **arrays, **{KEY: np.asarray(npz_checksum(arrays))})  # noqa: E731
    elif path.endswith(EXPORT_SUFFIXES):
        tmp = path[: path.rindex(".")] + ".tmp.pt2"  # torch.export.save expects its own suffix
        program = export_step(folded, dtype)
        extra = {KEY: program_checksum(program), ENVIRONMENT: json.dumps(environment(), sort_keys=True)}
        write = lambda: torch.export.save(program, tmp, extra_files=extra)  # noqa: E731
    else:
        raise ValueError(f"runtime path {path!r}: use a .npz (NumPy) or .pt2 (torch.export) file name")
    try:
        write()
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):  # a full disk, say: no half-written file left behind
            os.remove(tmp)
        raise
    return folded


def program_checksum(program: torch.export.ExportedProgram) -> str:
    """SHA-256 (hex) of a ``torch.export`` program's weights and constants: each tensor's name, dtype, shape and
    bytes, in sorted order (one flipped bit in a weight changes it)."""
    d = Digest()
    tensors = {**{f"state/{k}": v for k, v in program.state_dict.items()}, **{f"constant/{k}": v for k, v in program.constants.items()}}
    for name in sorted(tensors):
        value = tensors[name]
        d.array(name, value.detach().cpu().numpy() if torch.is_tensor(value) else np.asarray(repr(value)))
    return d.hexdigest()


class _Program(torch.nn.Module):
    """A loaded ``torch.export`` step that takes its inputs in any float dtype (h5py and NumPy give float64) and
    casts each to the program's own: ``(z_prev, z_prev2, p, p_prev, p_prev2, xD) -> (z, x)``, where ``z_prev`` is
    the newest latent (frame t-1) and ``z_prev2`` the one before it."""

    def __init__(self, program: torch.export.ExportedProgram):
        super().__init__()
        self.module_ = program.module()
        user = set(program.graph_signature.user_inputs)
        self.dtypes = [n.meta["val"].dtype for n in program.graph.nodes if n.op == "placeholder" and n.name in user]

    def forward(self, *args):
        if len(args) != len(self.dtypes):
            raise TypeError(f"the step takes {len(self.dtypes)} arguments (z_prev, z_prev2, p, p_prev, p_prev2, xD), got {len(args)}")
        return self.module_(*(torch.as_tensor(a).to(dt) for a, dt in zip(args, self.dtypes)))


def load_program(path) -> torch.nn.Module:
    """The ``torch.export`` step of a ``runtime.pt`` (``.pt2``), checked against the checksum it was written
    with, as a module that casts its inputs to the program's dtypes (:class:`_Program`).  A file that cannot
    be read or does not match its checksum is moved aside (``<name>.corrupt``, :func:`latentsim.checksum.corrupt`)."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file")
    extra = {KEY: ""}
    try:
        with open(path, "rb") as f:  # a file object: torch.export.load reads any suffix (runtime.pt) without a warning
            program = torch.export.load(f, extra_files=extra)
    except Exception as err:  # truncated or damaged: OSError, RuntimeError (zip), pickle errors, ...
        raise corrupt(path, f"torch.export cannot read it: {type(err).__name__}: {err}") from err
    stored = extra[KEY].decode() if isinstance(extra[KEY], bytes) else str(extra[KEY])
    if not stored:
        unverified(path)
    elif (actual := program_checksum(program)) != stored:
        raise corrupt(path, f"its weights do not match its checksum (sha256 {actual[:12]}..., recorded {stored[:12]}...)")
    return _Program(program)


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

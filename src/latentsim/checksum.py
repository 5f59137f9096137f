"""Checksums of artefacts, and what a reader does with a corrupt one.

Every artefact the pipeline writes stores a SHA-256 of its own content beside it, under the name
:data:`KEY` (``sha256``): HDF5 files as a root attribute (:mod:`latentsim.io`), PyTorch files as a
key of their dict (:mod:`latentsim.latent.serialization`), ``runtime.npz`` as an array
(:mod:`latentsim.runtime.files`).  The checksum is over content, not file bytes: each array's name,
dtype, shape and bytes, and each setting's name and ``repr``, in one fixed order (:class:`Digest`),
so it survives a rewrite of the container and catches one flipped bit in any value.

A reader that finds an artefact truncated, unreadable or not matching its checksum moves it aside
(to ``<name>.corrupt``) and raises :class:`ArtefactError` naming it (:func:`corrupt`): the file
Snakemake expected is then missing, so the same ``snakemake`` command run again reruns the job that
writes it (rule ``all`` lists the data artefacts of every scene's chain, as Snakemake rewrites a
missing file only when a job it runs needs it).  A file without a checksum (written before checksums were recorded) is read unverified,
with a warning (:func:`unverified`).

This module imports nothing from latentsim, so every layer (the deployable runtime included) can use it.
"""

from __future__ import annotations

import hashlib
import logging
import os

import numpy as np

__all__ = ["KEY", "ArtefactError", "Digest", "corrupt", "unverified"]

KEY = "sha256"  # where an artefact stores its checksum (attribute, dict key or array name)
BLOCK_BYTES = 1 << 25  # hash large arrays in blocks of about this size

log = logging.getLogger(__name__)
_warned: set[str] = set()


class ArtefactError(ValueError):
    """An input artefact is missing a key, holds a bad value, or is corrupt."""


class Digest:
    """SHA-256 over named arrays and settings, each framed by its name, type and shape.

    >>> d = Digest()
    >>> d.array("x", np.arange(3.0)); d.value("mode", "roots")
    >>> len(d.hexdigest())
    64
    """

    def __init__(self):
        self._h = hashlib.sha256()

    def _frame(self, *parts) -> None:
        self._h.update(repr(parts).encode() + b"\0")

    def array(self, name: str, a) -> None:
        """Add array ``a`` (any shape) under ``name``: its dtype, shape and C-order bytes; strings
        and objects by the ``repr`` of their list."""
        a = np.asarray(a)
        if a.dtype.kind in "OUS":
            self._frame("text", name, a.shape, repr(a.tolist()))
            return
        self._frame("array", name, a.dtype.str, a.shape)
        self._h.update(np.ascontiguousarray(a).reshape(-1).view(np.uint8))

    def blocks(self, name: str, dtype, shape, read) -> None:
        """Add an array of ``dtype`` and ``shape`` read in row blocks: ``read(start, stop)`` returns
        rows ``start:stop`` (the same bytes as :meth:`array` of the whole, without holding it)."""
        dtype = np.dtype(dtype)
        if dtype.kind in "OUS" or len(shape) == 0:
            self.array(name, read(None, None))
            return
        self._frame("array", name, dtype.str, tuple(shape))
        row = max(1, int(np.prod(shape[1:], dtype=np.int64)) * dtype.itemsize)
        step = max(1, BLOCK_BYTES // row)
        for start in range(0, shape[0], step):
            block = np.asarray(read(start, min(start + step, shape[0])), dtype=dtype)
            self._h.update(np.ascontiguousarray(block).reshape(-1).view(np.uint8))

    def value(self, name: str, v) -> None:
        """Add a setting (number, string, bool, None, list, tuple or dict of them) by its ``repr``."""
        self._frame("value", name, repr(v))

    def hexdigest(self) -> str:
        return self._h.hexdigest()


def corrupt(path, reason: str) -> ArtefactError:
    """Move the corrupt artefact ``path`` aside (``<name>.corrupt``) and return the error that says
    so and what to run; the caller raises it (``raise corrupt(path, why) from err``)."""
    path = os.fspath(path)
    aside = path + ".corrupt"
    done = f"moved aside to {aside}: the same snakemake command run again writes it anew (if that run has nothing to do, add {path} as a target)"
    try:
        os.replace(path, aside)
    except FileNotFoundError:  # another reader of the same file moved it first
        pass
    except OSError as err:
        done = f"it could not be moved aside ({err}): delete it, or rerun the job that writes it with snakemake --forcerun RULE"
    return ArtefactError(f"{path}: corrupt artefact ({reason}); {done}")


def unverified(path) -> None:
    """Warn, once per file, that ``path`` holds no checksum and is read unverified."""
    path = os.fspath(path)
    if path not in _warned:
        _warned.add(path)
        log.warning("%s: no %s checksum (written before checksums were recorded): read unverified; rerun its job to add one", path, KEY)

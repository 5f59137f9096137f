"""Artefact I/O: atomic writes and provenance attributes.

Every artefact is written to a hidden temporary name in its final folder and
renamed into place only once complete (``os.replace`` is atomic on POSIX), so a
job killed mid-write never leaves a file that Snakemake or a later stage takes
for complete.  Every HDF5 artefact carries, at its root:

- ``latentsim_version`` : package version,
- ``config`` : JSON of the config slice that produced it,
- ``seed`` : the random seed used (-1 when none applies).

The layout of each artefact is documented in ``docs/artefacts.md``.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np

from latentsim import __version__


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary sibling path; rename it to ``path`` on success.

    On any exception (or if the process dies) the final path is untouched; the
    temporary file is removed on exceptions.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            if tmp.is_dir():
                shutil.rmtree(tmp)
            else:
                tmp.unlink()
        raise


@contextlib.contextmanager
def atomic_h5(path, config=None, seed=-1):
    """Open an HDF5 file for writing under a temporary name, with provenance.

    >>> with atomic_h5("out.h5", config={"dt": 0.03}, seed=0) as f:
    ...     f["a"] = 1
    """
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w", track_order=True) as f:
            write_provenance(f, config, seed)
            yield f


def write_provenance(h5obj, config=None, seed=-1):
    """Record package version, config slice (JSON) and seed as attributes."""
    h5obj.attrs["latentsim_version"] = __version__
    h5obj.attrs["config"] = json.dumps(config if config is not None else {}, sort_keys=True)
    h5obj.attrs["seed"] = int(seed)


def read_config_attr(h5obj) -> dict:
    """Inverse of :func:`write_provenance` for the config slice."""
    return json.loads(h5obj.attrs["config"])


def write_dataset(group, name, data, **kwargs):
    """Write an array without timestamps, so identical runs give identical files."""
    data = np.asarray(data)
    return group.create_dataset(name, data=data, track_times=False, **kwargs)


class ArtefactError(ValueError):
    """An input artefact is missing a key or holds a bad value."""


def require(h5obj, key, path=None):
    """Return ``h5obj[key]`` or raise ArtefactError naming the file and key."""
    if key not in h5obj:
        where = path or getattr(h5obj.file, "filename", "?")
        raise ArtefactError(f"{where}: missing '{h5obj.name.rstrip('/')}/{key}'")
    return h5obj[key]


def write_tree(group, tree: dict):
    """Store a nested dict: dicts as groups, arrays as datasets, numbers, strings and lists of them as attributes."""
    for key, value in tree.items():
        if isinstance(value, dict):
            write_tree(group.create_group(key, track_order=True), value)
        elif isinstance(value, np.ndarray):
            write_dataset(group, key, value)
        else:
            group.attrs[key] = value


def read_tree(group) -> dict:
    """Inverse of :func:`write_tree` (attributes come back as NumPy scalars and arrays, strings as str)."""
    out = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in group.attrs.items()}
    for key, item in group.items():
        out[key] = read_tree(item) if isinstance(item, h5py.Group) else item[()]
    return out

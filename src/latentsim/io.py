"""Artefact I/O: atomic writes and provenance attributes.

Every artefact is written to a hidden temporary name in its final folder and
renamed into place only once complete (``os.replace`` is atomic on POSIX), so a
job killed mid-write never leaves a file that Snakemake or a later stage takes
for complete.  Every HDF5 artefact carries, at its root:

- ``latentsim_version`` : package version,
- ``config`` : JSON of the config slice that produced it,
- ``seed`` : the random seed used (-1 when none applies),
- ``environment`` : JSON of the processor and numerical libraries that computed it
  (:func:`latentsim.provenance.environment`),
- ``sha256`` : the checksum of everything else in the file (:func:`h5_checksum`), written last.

Readers open them with :func:`open_artefact`, which verifies the checksum and turns a truncated,
unreadable or altered file into an :class:`ArtefactError` naming it, after moving it aside so that
the next ``snakemake`` run regenerates it (:mod:`latentsim.checksum`).  CSV tables, which have no room
for one, get the SHA-256 of their bytes in a file beside them (``<name>.csv.sha256``, :func:`write_csv`),
checked the same way by :func:`read_csv`: a table with rows removed, cut mid-row or edited is named and
moved aside.

The layout of each artefact is documented in ``docs/artefacts.md``.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np

from latentsim import __version__
from latentsim.checksum import KEY, ArtefactError, Digest, corrupt, unverified
from latentsim.provenance import ENVIRONMENT, environment

__all__ = [
    "ArtefactError",
    "atomic_h5",
    "atomic_path",
    "h5_checksum",
    "open_artefact",
    "read_config_attr",
    "read_csv",
    "read_mesh_arrays",
    "read_tree",
    "require",
    "write_csv",
    "write_dataset",
    "write_provenance",
    "write_tree",
]


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


CSV_CHECKSUM = ".sha256"  # the suffix of a CSV table's checksum file: metrics.csv -> metrics.csv.sha256


def _checksum_path(path) -> Path:
    path = Path(path)
    return path.with_name(path.name + CSV_CHECKSUM)


def write_csv(df, path, **to_csv) -> None:
    """Write the DataFrame ``df`` as CSV (``to_csv``'s keywords) atomically, with the SHA-256 of its bytes in
    ``<path>.sha256`` (written first: a run killed between the two leaves a table whose checksum does not
    match, which :func:`read_csv` moves aside, never one that passes unchecked)."""
    with atomic_path(path) as tmp:
        df.to_csv(tmp, **to_csv)
        with atomic_path(_checksum_path(path)) as side:
            side.write_text(hashlib.sha256(tmp.read_bytes()).hexdigest() + "\n")


def read_csv(path, **read_csv_kw):
    """A CSV table the pipeline wrote (:func:`write_csv`), checked against its checksum file: one whose bytes do
    not match it (rows removed, cut mid-row, edited) or that pandas cannot read is moved aside and named
    (:func:`latentsim.checksum.corrupt`); one without a checksum file (written before they were) is read unverified."""
    import pandas as pd

    path = Path(path)
    data = path.read_bytes()
    side = _checksum_path(path)
    if side.exists():
        stored, actual = side.read_text().strip(), hashlib.sha256(data).hexdigest()
        if stored != actual:
            side.unlink(missing_ok=True)
            raise corrupt(path, f"its bytes do not match its checksum in {side.name} (sha256 {actual[:12]}..., recorded {stored[:12]}...): "
                                "rows removed, cut or edited")  # fmt: skip
    else:
        unverified(path)
    try:
        return pd.read_csv(io.BytesIO(data), **read_csv_kw)
    except Exception as err:  # empty, binary, ragged: pandas' ParserError, EmptyDataError, UnicodeDecodeError, ...
        side.unlink(missing_ok=True)
        raise corrupt(path, f"pandas cannot read it as CSV: {type(err).__name__}: {err}") from err


@contextlib.contextmanager
def atomic_h5(path, config=None, seed=-1):
    """Open an HDF5 file for writing under a temporary name, with provenance; on success its
    checksum (:func:`h5_checksum`) is stored as the root attribute ``sha256`` and it is renamed
    into place.

    >>> with atomic_h5("out.h5", config={"dt": 0.03}, seed=0) as f:
    ...     f["a"] = 1
    """
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w", track_order=True) as f:
            write_provenance(f, config, seed)
            yield f
            f.attrs[KEY] = h5_checksum(f)


def h5_checksum(f: h5py.File) -> str:
    """SHA-256 (hex) of an open HDF5 file's content: every group's and dataset's path, every
    attribute (but the root ``sha256`` itself) and every dataset's dtype, shape and bytes, in
    sorted order (independent of creation order and of the file's layout on disk)."""
    d = Digest()

    def visit(name: str, obj) -> None:
        for key in sorted(obj.attrs):
            if not (name == "/" and key == KEY):
                d.array(f"{name}@{key}", obj.attrs[key])
        if isinstance(obj, h5py.Dataset):
            if obj.shape is None:  # an empty (null) dataspace
                d.value(name, "empty")
            else:
                d.blocks(name, obj.dtype, obj.shape, lambda a, b: obj[()] if a is None else obj[a:b])
        else:
            d.value(name, "group")
            for key in sorted(obj):
                visit(f"{name.rstrip('/')}/{key}", obj[key])

    visit("/", f)
    return d.hexdigest()


_verified: set[tuple] = set()  # (path, inode, size, mtime) of files verified in this process


@contextlib.contextmanager
def open_artefact(path):
    """Open an HDF5 artefact for reading, checked: yields the open ``h5py.File``.

    The file's ``sha256`` attribute is compared with :func:`h5_checksum` of its content (once per
    process for an unchanged file); a file without one (written before checksums) is read with a
    warning.

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
        raise FileNotFoundError(f"{path}: no such artefact")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise corrupt(path, f"HDF5 cannot open it: {err}") from err
    with f:
        st = os.stat(path)
        stamp = (os.path.abspath(path), st.st_ino, st.st_size, st.st_mtime_ns)
        if stamp not in _verified:
            stored = f.attrs.get(KEY)
            if stored is None:
                unverified(path)
            else:
                try:
                    actual = h5_checksum(f)
                except Exception as err:  # damaged metadata or chunks: HDF5 raises OSError, KeyError, RuntimeError, ...
                    f.close()
                    raise corrupt(path, f"HDF5 cannot read it: {err}") from err
                stored = stored.decode() if isinstance(stored, bytes) else str(stored)
                if actual != stored:
                    f.close()
                    raise corrupt(path, f"its content does not match its checksum (sha256 {actual[:12]}..., recorded {stored[:12]}...)")
            _verified.add(stamp)
        yield f


def write_provenance(h5obj, config=None, seed=-1):
    """Record package version, config slice (JSON), seed and the computing environment (JSON of
    :func:`latentsim.provenance.environment`) as attributes."""
    h5obj.attrs["latentsim_version"] = __version__
    h5obj.attrs["config"] = json.dumps(config if config is not None else {}, sort_keys=True)
    h5obj.attrs["seed"] = int(seed)
    h5obj.attrs[ENVIRONMENT] = json.dumps(environment(), sort_keys=True)


def read_mesh_arrays(path) -> dict:
    """A mesh artefact's arrays (``results/mesh/<scene>/mesh.h5``: rest positions, elements, Dirichlet set, ...) and
    its ``model``, read checked (:func:`open_artefact`)."""
    with open_artefact(path) as f:
        arrays = {k: f[k][()] for k in f.keys()}
        arrays["model"] = str(f.attrs["model"])
    return arrays


def read_config_attr(h5obj) -> dict:
    """Inverse of :func:`write_provenance` for the config slice."""
    return json.loads(h5obj.attrs["config"])


def write_dataset(group, name, data, **kwargs):
    """Write an array without timestamps, so identical runs give identical files."""
    data = np.asarray(data)
    return group.create_dataset(name, data=data, track_times=False, **kwargs)


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

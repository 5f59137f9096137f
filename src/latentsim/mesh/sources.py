"""Pinned public meshes and :func:`fetch_mesh`: a verified local copy of a mesh file.

Mesh files are never part of the repository: :func:`fetch_mesh` takes them
from a local folder named in the config (e.g. ``../shared/meshes``), from the
download cache, or downloads the pinned URL of :data:`MESH_SOURCES`, and checks
the sha256 either way, so an unverified file is never used or cached.
"""

from __future__ import annotations

import difflib
import hashlib
import logging
import os
import re
import tempfile
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

from latentsim.mesh.validation import MeshError

logger = logging.getLogger(__name__)

_NEURAL_MODES = (
    "https://raw.githubusercontent.com/jiahong-w/neural-modes/"
    "233aa77b12ac0ecf7503f49560f12510cfbb4eb6/datasets"
)

#: Pinned public meshes: file name -> url, sha256 (plus licence and the counts
#: the file holds, for reference).  Facts copied from ``shared/meshes/SOURCES.md``.
MESH_SOURCES: dict[str, dict[str, Any]] = {
    "armadillo.vtu": {
        "url": f"{_NEURAL_MODES}/armadillo/ref.vtu",
        "sha256": "cc260f19b94cb43f308e91689dc9bd7826d9e849bc68743380c972631fe38a43",
        "licence": "Apache-2.0 (c) 2024 Jiahong Wang",
        "vertices": 7179,
        "tets": 26211,
    },
    "giraffe.vtu": {
        "url": f"{_NEURAL_MODES}/giraffe/ref.vtu",
        "sha256": "abb7a510bad351b93893460572141811af9520d39c81b9fb793fee81e9491e01",
        "licence": "Apache-2.0 (c) 2024 Jiahong Wang",
        "vertices": 1698,
        "tets": 5424,
    },
    "square.obj": {
        "url": f"{_NEURAL_MODES}/square/ref.obj",
        "sha256": "61990f9667badee8a5ac9d51152b83b6d0c684bd663241847cf3d43934013849",
        "licence": "Apache-2.0 (c) 2024 Jiahong Wang",
        "vertices": 121,
        "triangles": 200,
    },
    "bunny.obj": {
        "url": "https://raw.githubusercontent.com/evouga/libshell/"
        "6072d9e4b3c9f99c8cfe538b8b5560954d87dfdf/example/bunny.obj",
        "sha256": "b8cedb0c8027f0d73f56c192751a6d307b5b8b863642a850a7f2b03af41cebf8",
        "licence": "MPL-2.0 (libshell)",
        "vertices": 2823,
        "triangles": 5642,
    },
    "coarse_bunny.mesh": {
        "url": "https://raw.githubusercontent.com/lawsonfulton/AutoDef/"
        "ce530cc91806d9c3acbe8b2b7cdea1d6dc37157c/meshes/coarsebunny.mesh",
        "sha256": "59aefe2888359522742404117d840af42288dddb2771188f96932b7f58392989",
        "licence": "MIT (c) 2019 Lawson Fulton",
        "vertices": 739,
        "tets": 2352,
    },
}

#: Where :func:`fetch_mesh` downloads to when no ``cache_dir`` is given
#: (``$LATENTSIM_CACHE/meshes``, default ``~/.cache/latentsim/meshes``).
DEFAULT_CACHE_DIR = (
    Path(os.environ.get("LATENTSIM_CACHE", Path.home() / ".cache" / "latentsim")) / "meshes"
)


def sha256_of(path: str | os.PathLike) -> str:
    """Hex sha256 digest of a file, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _verify(actual: str, expected: str, where: str) -> None:
    """Raise, naming the file and both hashes, unless ``actual == expected``."""
    if actual != expected:
        raise MeshError(f"{where}: sha256 mismatch, expected {expected}, got {actual}")


def _pinned(name: str, url: str | None, sha256: str | None) -> tuple[str | None, str]:
    """The url and (lower-case) sha256 for ``name``: the arguments, else its :data:`MESH_SOURCES` entry."""
    if not name or Path(name).name != name or name in (".", ".."):
        raise MeshError(f"mesh name must be a plain file name, got {name!r}")
    entry = MESH_SOURCES.get(name, {})
    url = url if url is not None else entry.get("url")
    sha256 = sha256 if sha256 is not None else entry.get("sha256")
    if not sha256:
        raise MeshError(
            f"no sha256 pinned for mesh {name!r}: pass sha256= (known meshes: "
            f"{', '.join(sorted(MESH_SOURCES))})"
        )
    sha256 = sha256.lower()
    if not re.fullmatch(r"[0-9a-f]{64}", sha256):
        raise MeshError(f"mesh {name!r}: sha256 must be 64 hex digits, got {sha256!r}")
    return url, sha256


def _download(name: str, url: str, sha256: str, cache: Path, timeout: float) -> Path:
    """Download ``url`` to ``cache/name`` through a temporary file, renamed into place once verified."""
    cache.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{name}.", suffix=".part", dir=cache)
    tmp = Path(tmp_name)
    target = cache / name
    try:
        h = hashlib.sha256()
        with os.fdopen(fd, "wb") as out:
            try:
                with urllib.request.urlopen(url, timeout=timeout) as response:
                    for chunk in iter(lambda: response.read(1 << 20), b""):
                        h.update(chunk)
                        out.write(chunk)
            except (urllib.error.URLError, OSError, ValueError) as exc:
                raise MeshError(f"mesh {name!r}: download from {url} failed: {exc}") from exc
        _verify(h.hexdigest(), sha256, f"downloaded mesh {name!r} from {url}")
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()
    logger.info("mesh %s: downloaded %s -> %s (sha256 ok)", name, url, target)
    return target


def fetch_mesh(
    name: str,
    local_dir: str | os.PathLike | None = None,
    cache_dir: str | os.PathLike | None = None,
    url: str | None = None,
    sha256: str | None = None,
    timeout: float = 60.0,
) -> Path:
    """Return a verified local path to the mesh file ``name``.

    Order of preference:

    1. ``local_dir/name`` if ``local_dir`` is given and holds the file: its
       sha256 is checked (a mismatch raises, it does not fall back to a
       download) and that path is returned as is (nothing is copied).
    2. ``cache_dir/name`` if it exists with the right sha256.
    3. Download ``url`` into ``cache_dir`` through a temporary file in the same
       folder, check the sha256, then rename it into place.  On any failure the
       temporary file is removed, so the cache never holds an unverified file.

    Parameters
    ----------
    name : str
        Plain file name (no folders), e.g. ``"armadillo.vtu"``.
    local_dir : path, optional
        Folder of pre-fetched meshes (config ``mesh_dir``, e.g. ``../shared/meshes``).
    cache_dir : path, optional
        Download folder; default :data:`DEFAULT_CACHE_DIR`.
    url, sha256 : str, optional
        Override the pinned entry of :data:`MESH_SOURCES`; required for files
        not listed there.  A sha256 is always required.
    timeout : float
        Seconds for the download connection.

    Returns
    -------
    Path
        Path of the verified file.

    Raises
    ------
    MeshError
        Unknown name without url/sha256, hash mismatch (naming the file, the
        expected and the actual hash), or a failed download.
    """
    url, sha256 = _pinned(name, url, sha256)
    if local_dir is not None:
        local = Path(local_dir) / name
        if local.is_file():
            _verify(sha256_of(local), sha256, f"local mesh {name!r} ({local})")
            logger.info("mesh %s: using local file %s (sha256 ok)", name, local)
            return local
        logger.info("mesh %s: not in local folder %s, trying cache/download", name, local_dir)

    cache = Path(cache_dir) if cache_dir is not None else DEFAULT_CACHE_DIR
    target = cache / name
    if target.is_file():
        if sha256_of(target) == sha256:
            logger.info("mesh %s: using cached %s (sha256 ok)", name, target)
            return target
        logger.warning("mesh %s: cached %s has a wrong sha256, downloading again", name, target)
    if not url:
        raise MeshError(f"mesh {name!r} is not available locally and has no url to download")
    return _download(name, url, sha256, cache, timeout)


def user_mesh_path(file: str, sources: dict) -> Path | None:
    """The path of a user's own mesh file, or None for a pinned mesh (see :func:`mesh_file`).

    ``file`` is a pinned mesh when it is a plain file name listed in :data:`MESH_SOURCES`.
    Otherwise it is the user's: a plain name is looked for in ``sources['local_dir']``
    (when set), anything else is a path (relative to the working directory).
    """
    if file in MESH_SOURCES:
        return None
    local_dir = sources.get("local_dir")
    if local_dir is not None and Path(file).name == file:
        return Path(local_dir) / file
    return Path(file)


def check_user_mesh(file: str, sources: dict, where: str = "mesh.file") -> Path | None:
    """:func:`user_mesh_path`, checked: the user's file must exist (None for a pinned mesh).

    Called when the workflow loads its config, so that a mistyped path stops the run
    before any job, and by :func:`mesh_file` when the mesh is built.

    Raises
    ------
    MeshError
        The user's file is missing; the message names ``where``, the path, the
        folder a relative path is read from and the closest names found there.
    """
    path = user_mesh_path(file, sources)
    if path is None or path.is_file():
        return path
    folder = path.parent
    if path.is_absolute():
        base = ""
    elif sources.get("local_dir") is not None and Path(file).name == file:
        base = f" (a bare file name is read from meshes.local_dir, {str(folder)!r})"
    else:
        base = f" (a path is read relative to the working directory, {str(Path.cwd())!r})"
    if folder.is_dir():
        close = difflib.get_close_matches(path.name, sorted(p.name for p in folder.iterdir()), n=3)
        hint = f"; did you mean {', '.join(repr(str(folder / c)) for c in close)}?" if close else ""
    else:
        hint = f"; folder {str(folder)!r} does not exist"
    raise MeshError(
        f"{where}: mesh file {str(path)!r} not found{base}{hint} (pinned meshes, read from "
        f"meshes.local_dir or downloaded: {', '.join(sorted(MESH_SOURCES))})")


def mesh_file(file: str, sources: dict, sha256: str | None = None, where: str = "mesh.file") -> Path:
    """A verified local path for a scene's ``mesh.file`` (and optional ``mesh.sha256``).

    A pinned mesh (a name in :data:`MESH_SOURCES`) goes through :func:`fetch_mesh`
    with its pinned hash (or ``sha256`` when given).  A user's own file
    (:func:`user_mesh_path`) is read where it is; its sha256 is checked only when
    ``sha256`` is given, so a mesh of one's own needs no entry in the package.

    Raises
    ------
    MeshError
        Missing file, bad or mismatching sha256; the message names ``where`` and the path.
    """
    path = check_user_mesh(file, sources, where)
    if path is None:
        return fetch_mesh(file, local_dir=sources.get("local_dir"),
                          cache_dir=sources["cache_dir"], sha256=sha256)
    if sha256 is not None:
        expected = sha256.lower()
        if not re.fullmatch(r"[0-9a-f]{64}", expected):
            raise MeshError(f"{where}: sha256 must be 64 hex digits, got {sha256!r}")
        _verify(sha256_of(path), expected, f"{where}: mesh file {str(path)!r}")
    logger.info("mesh %s: using the user's file %s%s", file, path,
                " (sha256 ok)" if sha256 is not None else "")
    return path

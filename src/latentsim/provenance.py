"""The machine and numerical libraries an artefact was computed with.

Every artefact records :func:`environment` beside its results, under :data:`ENVIRONMENT`
(``environment``): HDF5 files as a root attribute holding JSON (:func:`latentsim.io.write_provenance`),
PyTorch files as a key of their dict (:func:`latentsim.latent.serialization.atomic_save`),
``runtime.npz`` as a JSON string array (:func:`latentsim.runtime.export_runtime`).  Each is covered
by the artefact's checksum like any other value, and left out of fingerprint comparisons
(:data:`latentsim.fingerprint.SKIPPED_ATTRS`): it says where a result was computed, not what it is.

Why it matters (``docs/methods.md``, "What matches to the bit and what in distribution"): on the same
processor, seed and library versions every artefact is the same to the bit; trained networks and
what is computed from them differ between processors in the last bits of rounding, so a learned result
from another machine compares only in distribution.

This module imports nothing from latentsim, so every layer (the deployable runtime included) can use it.

Command line::

    python -m latentsim.provenance                   # this machine's environment
    python -m latentsim.provenance ARTEFACT [...]    # the environment each artefact records
"""

from __future__ import annotations

import argparse
import functools
import importlib.metadata
import json
import os
import platform
import re
import sys

__all__ = ["ENVIRONMENT", "environment", "machine_signature", "recorded_environment"]

ENVIRONMENT = "environment"  # where an artefact records it (attribute, dict key or array name)
LIBRARIES = ("numpy", "scipy", "torch", "h5py")


def processor() -> str:
    """The processor's model name (``/proc/cpuinfo``), else what :mod:`platform` knows of it."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(name: str) -> str | None:
    """The installed version of package ``name`` (None where it is not installed)."""
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        module = sys.modules.get(name)
        return getattr(module, "__version__", None)


@functools.lru_cache(maxsize=1)
def _fixed() -> dict:
    """What does not change while a process runs: processor, system, versions, NumPy's BLAS."""
    import numpy as np

    env = {
        "processor": processor(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "os": platform.platform(),
        "python": platform.python_version(),
        **{name: _version(name) for name in LIBRARIES},
    }
    try:
        deps = np.show_config(mode="dicts").get("Build Dependencies", {})
    except (TypeError, AttributeError):  # NumPy before 1.25 only prints its configuration
        deps = {}
    for lib in ("blas", "lapack"):
        info = deps.get(lib, {})
        env[f"numpy_{lib}"] = " ".join(str(info[k]) for k in ("name", "version") if info.get(k)) or None
    return env


@functools.lru_cache(maxsize=1)
def _torch_build() -> dict:
    """Torch's BLAS and LAPACK (from its build settings) and the vector instructions its kernels use."""
    import torch

    settings = dict(re.findall(r"\b(BLAS_INFO|LAPACK_INFO)=([^,\s]+)", torch.__config__.show()))
    capability = getattr(getattr(torch.backends, "cpu", None), "get_cpu_capability", None)
    return {
        "torch_blas": settings.get("BLAS_INFO"),
        "torch_lapack": settings.get("LAPACK_INFO"),
        "torch_cpu_capability": capability() if capability else None,
    }


def environment() -> dict:
    """The processor and the numerical libraries this process computes with.

    Returns
    -------
    dict
        ``processor`` (model name), ``machine`` (architecture), ``cpus``, ``os``, ``python``; the
        versions of ``numpy``, ``scipy``, ``torch`` and ``h5py`` (None where not installed);
        ``numpy_blas`` and ``numpy_lapack`` (the libraries NumPy was built with); and, where this
        process has loaded torch (else None: it computed nothing with it), ``torch_threads``,
        ``torch_blas``, ``torch_lapack`` and ``torch_cpu_capability`` (the vector instructions its
        kernels use, e.g. ``AVX2``).

    Notes
    -----
    Everything but the torch thread count is read once per process; a call costs microseconds.
    """
    env = dict(_fixed())
    torch = sys.modules.get("torch")
    if torch is not None and hasattr(torch, "get_num_threads"):
        env["torch_threads"] = torch.get_num_threads()
        env.update(_torch_build())
    else:
        env.update(dict.fromkeys(("torch_threads", "torch_blas", "torch_lapack", "torch_cpu_capability")))
    return env


def machine_signature() -> str:
    """Processor model and numeric library versions in one line: bitwise comparisons of two runs hold
    only where these match (the ``machine`` of a recorded fingerprint, :mod:`latentsim.fingerprint`)."""
    env = _fixed()
    return f"{env['processor']} | numpy {env['numpy']} | torch {env['torch']}"


def recorded_environment(path) -> dict | None:
    """The environment an artefact (``.h5``, ``.pt`` or ``.npz``) records; None for one written
    before environments were recorded.  Read as the file is, unchecked (its checksum is verified
    by the pipeline's readers, :mod:`latentsim.checksum`)."""
    path = os.fspath(path)
    if path.endswith(".h5"):
        import h5py

        with h5py.File(path, "r") as f:
            value = f.attrs.get(ENVIRONMENT)
    elif path.endswith(".pt"):
        import torch

        value = torch.load(path, map_location="cpu", weights_only=True).get(ENVIRONMENT)
    elif path.endswith(".npz"):
        import numpy as np

        with np.load(path, allow_pickle=False) as z:
            value = str(z[ENVIRONMENT]) if ENVIRONMENT in z.files else None
    else:
        raise ValueError(f"{path}: not an artefact (.h5, .pt or .npz)")
    if isinstance(value, bytes):
        value = value.decode()
    return json.loads(value) if isinstance(value, str) else value


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m latentsim.provenance", description=__doc__.split("\n\n")[0])
    parser.add_argument("artefacts", nargs="*", help=".h5, .pt or .npz files (none: this machine's environment)")
    args = parser.parse_args(argv)
    if not args.artefacts:
        print(json.dumps(environment(), indent=2))
        return 0
    here = _fixed()
    for path in args.artefacts:
        env = recorded_environment(path)
        if env is None:
            print(f"{path}: no environment recorded (written before environments were)")
            continue
        print(f"{path}:")
        print(json.dumps(env, indent=2))
        differ = [k for k in here if k in env and env[k] != here[k]]
        print(f"  differs from this machine in: {', '.join(differ)}" if differ else "  same processor and libraries as this machine")
    return 0


if __name__ == "__main__":
    sys.exit(main())

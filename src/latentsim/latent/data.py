"""The latent method's training data (Li et al. 2025, sec. 3.3): the simulator's sequences of
one split (:func:`load_sequences`, from ``trajectories.h5``) and the latent integrator's
ground-truth triplets ``(z_t, z_{t-1}, z_{t-2})`` with their boundary conditions
(:func:`build_triplets`, rows named by :data:`BATCH_KEYS`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from latentsim.io import open_artefact, require
from latentsim.latent.autoencoder import Autoencoder, encode_positions
from latentsim.latent.coordinates import RelativeCoordinates
from latentsim.latent.integrator import boundary_inputs

BATCH_KEYS = ("z", "z_prev", "z_prev2", "p", "p_prev", "p_prev2", "xD", "xD_prev", "xD_prev2")


def load_sequences(f, split=None) -> dict:
    """{name: {positions, dirichlet_positions, bc, split}} of one split (or all) of an open
    ``trajectories.h5``; positions (T, n, 3), dirichlet_positions (T, m, 3), bc (T, k)."""
    out = {}
    for name, g in require(f, "sequences").items():
        if split is not None and g.attrs["split"] != split:
            continue
        out[name] = {k: g[k][()] for k in ("positions", "dirichlet_positions", "bc")}
        out[name]["split"] = str(g.attrs["split"])
    if not out:
        raise ValueError(f"{f.filename}: no sequence with split '{split}'")
    return out


def load_split(paths, split=None) -> dict:
    """:func:`load_sequences` of one split of several ``trajectories.h5`` of one mesh (the
    conditions of a conditioned scene), each name prefixed with its file's stem and a dot; a
    single path's names as they are.

    Raises ValueError naming the file whose rest positions differ from the first's.
    """
    paths = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    out, rest = {}, None
    for path in paths:
        with open_artefact(path) as f:
            x = f["rest_positions"][()]
            if rest is None:
                rest = x
            elif x.shape != rest.shape or not np.array_equal(x, rest):
                raise ValueError(f"{path}: its rest positions differ from those of {paths[0]}; the sequences of one model share one mesh")
            prefix = "" if len(paths) == 1 else f"{Path(path).stem}."
            out.update({prefix + k: v for k, v in load_sequences(f, split).items()})
    return out


def triplet_rows(sequences: Sequence[dict]) -> list[int]:
    """How many rows :func:`build_triplets` makes of each sequence that gives any (T - 2 of a
    sequence of T >= 3 frames), in its order."""
    return [len(s["positions"]) - 2 for s in sequences if len(s["positions"]) >= 3]


def build_triplets(ae: Autoencoder, coords: RelativeCoordinates, sequences: Sequence[dict], origin: bool = False) -> dict:
    """Ground-truth training triplets of all sequences.

    Each sequence dict holds ``positions`` (T, n, 3), ``dirichlet_positions``
    (T, m, 3) and optionally ``bc`` (T, k) (absent -> k = 0); with ``origin`` each p_t gains the
    frame's mean prescribed position (:func:`~latentsim.latent.integrator.boundary_inputs`).  Latents are the
    frozen autoencoder's encodings.  Returns a dict with the keys of
    :data:`BATCH_KEYS`, N = sum_s (T_s - 2) rows each (latents/BCs float32,
    Dirichlet positions float64, on the autoencoder's device).
    """
    parts: dict[str, list] = {k: [] for k in BATCH_KEYS}
    dev = ae.pca_in.weight.device
    for s in sequences:
        x = torch.as_tensor(s["positions"]).to(torch.float64)
        xD = torch.as_tensor(s["dirichlet_positions"]).to(torch.float64)
        T = x.shape[0]
        bc = s.get("bc")
        bc = np.zeros((T, 0)) if bc is None else np.asarray(bc).reshape(T, -1)
        bc = torch.as_tensor(boundary_inputs(bc, s["dirichlet_positions"], origin, coords)).to(dev, torch.float32)
        if T < 3:
            continue
        z = encode_positions(ae, coords, x, xD)
        xD = xD.to(dev)
        for key, arr in (("z", z), ("p", bc), ("xD", xD)):
            parts[key].append(arr[2:])
            parts[key + "_prev"].append(arr[1:-1])
            parts[key + "_prev2"].append(arr[:-2])
    if not parts["z"]:
        raise ValueError("no training triplets: every sequence needs at least 3 frames")
    return {k: torch.cat(v) for k, v in parts.items()}


"""Fingerprints of a run's artefacts, to tell whether a change of the code changed its results.

A fingerprint holds, for every array in a results tree (HDF5 datasets and attributes, the state dicts
of ``.pt`` files (but the PyTorch program ``runtime.pt``), ``.npz`` runtimes, the numeric columns of CSV tables), its shape, dtype, the SHA-256
of its bytes and two float sums (sum and sum of absolute values).  Wall-clock measurements (names
ending in ``_ms`` or ``_seconds``, and the runtime a rollout chose by timing) are left out: they are
the only values two identical runs may differ in.

Two fingerprints are compared in one of two ways:

- **bitwise**: every digest equal.  Only meaningful on the processor that recorded the reference:
  training is sensitive to the last bit of rounding, which differs between processors.
- **to a tolerance**: the sums agree to ``rtol`` of their scale; used for the full-space artefacts
  (meshes and simulations), which converge to the Newton tolerance whatever the processor.

Files are read as they are (``h5py``, ``torch.load``, ``np.load``), not through the checked
readers of :mod:`latentsim.checksum`: a fingerprint describes whatever a results tree holds (files
written before checksums included, and a corrupt file is not moved aside), and an altered value shows
as a differing digest.  The artefacts' own ``sha256`` checksums are left out, as they cover wall times,
and so is the computing environment they record (:mod:`latentsim.provenance`): it says where a result
was computed, not what it is.

Command line::

    python -m latentsim.fingerprint record RESULTS OUT.json      # fingerprint a results tree
    python -m latentsim.fingerprint compare REF.json RESULTS     # what differs, bitwise
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import sys
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import torch

from latentsim.checksum import KEY
from latentsim.provenance import ENVIRONMENT, machine_signature

# attributes that record wall time or a choice made by timing
TIMING_NAMES = frozenset({"seconds", "runtime", "frame_ms", "step_ms"})
# provenance: the package version and the validated config slice, which lists every setting with its
# default (a setting added to the schema with the value the code already used changes it, not the results),
# the artefact's own checksum (latentsim.checksum.KEY), which covers its wall times too, and the processor
# and libraries that computed it (latentsim.provenance.ENVIRONMENT; also a key of .pt and .npz files)
SKIPPED_ATTRS = frozenset({"latentsim_version", "config", KEY, ENVIRONMENT})
# results/<stage>/... whose arrays converge to the Newton tolerance on any processor
PHYSICS_STAGES = ("mesh", "sim")


TIMING_WORDS = re.compile(r"(^|[ _/])(ms|s|seconds|speedup|over_floor|on_front)($|[ _/])")


def is_timing(name: str) -> bool:
    """A wall-time value, or a choice made from one (the speed-accuracy front), by name: these may
    differ between two identical runs.  Names are the pipeline's: ``step_ms``, ``ms/step mean``,
    ``train s``, ``speedup``, ``step_over_floor`` (a step's time over its floor's), ``on_front``."""
    leaf = name.rsplit("/", 1)[-1].rsplit("@", 1)[-1]
    return is_timing_word(leaf)


def is_timing_word(word: str) -> bool:
    """``is_timing`` of one name as it is: an attribute's, a state dict key's, a CSV column's (whose
    '/' is part of it, as in ``ms/step median``, not a path)."""
    return word in TIMING_NAMES or bool(TIMING_WORDS.search(word))


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]  # 64 bits: a collision by chance is not a concern here


def _entry(value) -> dict:
    a = np.asarray(value)
    if a.dtype.kind in "OUS":
        data = repr(a.tolist()).encode()
        return {"shape": list(a.shape), "dtype": "str", "sha256": _digest(data)}
    a = np.ascontiguousarray(a)
    out = {"shape": list(a.shape), "dtype": a.dtype.str, "sha256": _digest(a.tobytes())}
    if a.dtype.kind in "fiub" and a.size:
        f = a.astype(np.float64)
        finite = np.isfinite(f)
        out["sum"] = float(f[finite].sum())
        out["abs"] = float(np.abs(f[finite]).sum())
        out["nonfinite"] = int((~finite).sum())
    return out


def _h5(path: Path) -> dict:
    out = {}

    def visit(name, obj):
        for k, v in obj.attrs.items():
            if not is_timing(k) and k not in SKIPPED_ATTRS:
                out[f"{name}@{k}"] = _entry(v)
        if isinstance(obj, h5py.Dataset) and not is_timing(name):
            out[name] = _entry(obj[()])

    with h5py.File(path, "r") as f:
        visit("/", f)
        f.visititems(visit)
    return out


def _tensors(obj, prefix: str, out: dict) -> None:
    if isinstance(obj, dict):
        for k, v in obj.items():
            if not is_timing(str(k)):
                _tensors(v, f"{prefix}/{k}", out)
    elif torch.is_tensor(obj):
        out[prefix] = _entry(obj.detach().cpu().numpy())
    elif obj is not None:  # settings: numbers, strings, lists of them
        out[prefix] = _entry(np.asarray(repr(obj)))


def _pt(path: Path) -> dict:
    blob = torch.load(path, weights_only=True, map_location="cpu")
    for key in (KEY, ENVIRONMENT):
        blob.pop(key, None)
    out: dict = {}
    _tensors(blob, "", out)
    return out


def _npz(path: Path) -> dict:
    with np.load(path) as z:
        return {k: _entry(z[k]) for k in z.files if k not in (KEY, ENVIRONMENT)}


def _csv(path: Path) -> dict:
    """One entry per row, named by the row's text cells (scene, method, ...): its numbers, timing
    columns left out.  Rows are matched by name, so a table sorted by speed compares as well."""
    df = pd.read_csv(path)
    df = df[[c for c in df.columns if not is_timing_word(str(c))]]
    text = [c for c in df.columns if df[c].dtype.kind not in "fiub"]
    numbers = [c for c in df.columns if c not in text]
    out: dict = {"columns": _entry(np.asarray(list(map(str, df.columns))))}
    for i in range(len(df)):
        name = "row " + "/".join(str(df[c].iloc[i]) for c in text)
        while name in out:  # rows with the same text cells: numbered in file order
            name += "'"
        out[name] = _entry(df[numbers].iloc[i].to_numpy(np.float64))
    return out


READERS = {".h5": _h5, ".pt": _pt, ".npz": _npz, ".csv": _csv}


def fingerprint_tree(results: str | Path) -> dict:
    """{relative path: {array name: entry}} for every artefact under ``results``."""
    results = Path(results)
    # runtime.pt is the deployable PyTorch program of the networks that runtime.npz holds as arrays
    files = sorted(p for p in results.rglob("*") if p.suffix in READERS and p.is_file() and p.name != "runtime.pt")
    return {str(p.relative_to(results)): READERS[p.suffix](p) for p in files}


def record(results: str | Path) -> dict:
    return {"machine": machine_signature(), "files": fingerprint_tree(results)}


def _close(a: dict, b: dict, rtol: float) -> bool:
    if a["shape"] != b["shape"] or a.get("nonfinite") != b.get("nonfinite"):
        return False
    if "sum" not in a:
        return a["sha256"] == b["sha256"]
    scale = max(a["abs"], b["abs"], 1e-300)
    return abs(a["sum"] - b["sum"]) <= rtol * scale and abs(a["abs"] - b["abs"]) <= rtol * scale


def compare(reference: dict, current: dict, rtol: float | None = None, only=None, skip_name=None) -> list[str]:
    """What differs between two ``{path: {name: entry}}`` maps: bitwise (``rtol`` None) or to ``rtol``.

    ``only``: a predicate on the relative path choosing the files to compare; ``skip_name``: one on
    (path, array name) leaving arrays out.  A file or array that one side has and the other lacks
    is a difference.
    """
    problems = []
    for path in sorted(set(reference) | set(current)):
        if only is not None and not only(path):
            continue
        if path not in current or path not in reference:
            problems.append(f"{path}: only in the {'reference' if path in reference else 'current run'}")
            continue
        ref, cur = reference[path], current[path]
        for name in sorted(set(ref) | set(cur)):
            if skip_name is not None and skip_name(path, name):
                continue
            if name not in ref or name not in cur:
                problems.append(f"{path}:{name}: only in the {'reference' if name in ref else 'current run'}")
            elif (ref[name]["sha256"] != cur[name]["sha256"]) if rtol is None else not _close(ref[name], cur[name], rtol):
                problems.append(f"{path}:{name}: differs ({ref[name].get('sum')} vs {cur[name].get('sum')})")
    return problems


# a simulation's record of how Newton got to each frame, not the frame: the residual it stopped at and the
# iterations it took differ with the processor's rounding (one iteration more or less, a residual below the
# tolerance), where the positions agree to it
SOLVER_RECORDS = frozenset({"gradient_norm", "newton_iterations"})


def is_solver_record(path: str, name: str) -> bool:
    """An array of a full-space artefact that records the solver's path (:data:`SOLVER_RECORDS`)."""
    return is_physics(path) and name.rsplit("/", 1)[-1] in SOLVER_RECORDS


def is_physics(path: str) -> bool:
    """A full-space artefact (mesh or simulation, a conditioned scene's ``conditioned/<scene>/sim/``
    included): equal to the Newton tolerance on any processor."""
    parts = path.split("/")
    return parts[0] in PHYSICS_STAGES or (parts[0] == "conditioned" and len(parts) > 3 and parts[2] == "sim")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m latentsim.fingerprint", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="fingerprint a results tree into a JSON file")
    rec.add_argument("results")
    rec.add_argument("out")
    cmp = sub.add_parser("compare", help="compare a results tree with a recorded fingerprint")
    cmp.add_argument("reference")
    cmp.add_argument("results")
    cmp.add_argument("--rtol", type=float, default=None, help="compare sums to this tolerance instead of bitwise")
    args = parser.parse_args(argv)
    if args.command == "record":
        rec = record(args.results)
        # one line per file, so that a diff of two recordings names the files that changed
        lines = [f'  "{k}": {json.dumps(v, sort_keys=True)}' for k, v in rec["files"].items()]
        text = '{"machine": ' + json.dumps(rec["machine"]) + ',\n "files": {\n' + ",\n".join(lines) + "\n}}\n"
        Path(args.out).write_text(text)
        print(f"{args.out}: {len(lines)} files")
        return 0
    ref = json.loads(Path(args.reference).read_text())
    problems = compare(ref["files"], fingerprint_tree(args.results), args.rtol)
    if ref["machine"] != machine_signature() and args.rtol is None:
        print(f"note: recorded on '{ref['machine']}', this machine is '{machine_signature()}'", file=sys.stderr)
    print("\n".join(problems) if problems else "all equal")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())

"""A latent runtime against an earlier revision's, on the pipeline's trained runtimes.

Loads the runtime package ``src/latentsim/runtime/`` as it was at ``--against`` (``git show``; before
the layout by domain, ``src/latentsim/runtime.py`` and ``runtime_compiled.py``) beside the working
tree's, its NumPy stepper (``--runtime numpy``, the default) or its compiled one (``--runtime compiled``),
and times one whole latent step (integration + decoding to every vertex) of each scene's exported
runtime (``<results>/rollout/<scene>/<method>/seed<k>/runtime.npz`` of seed ``--seed``, default 0, or the files
given with ``--npz``)
with both.  The two alternate in rounds, so that the shared machine's noise hits both alike; the
figures are medians over the rounds of each round's median.  One thread, float32 networks, as the
rollout stage times them.

    python benchmarks/bench_runtime_ab.py --against 068298f [--results results] [--scenes armadillo cloth]
    python benchmarks/bench_runtime_ab.py --against HEAD~1 --rounds 7 --repeats 2000 [--seed 1]
    python benchmarks/bench_step_floor.py bunny_ears hair_rotation --export floors   # untrained floor networks
    python benchmarks/bench_runtime_ab.py --runtime compiled --against 9e32a90 --npz floors/*.npz

Prints, per scene: the relative-coordinate mode, the decode layout, both step times [us], their
ratio, and the largest difference between the two runtimes' decoded positions.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import importlib  # noqa: E402
import importlib.util  # noqa: E402
import re  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from latentsim import runtime as current  # noqa: E402
from latentsim.config import seed_dir  # noqa: E402
from latentsim.runtime import compiled as current_compiled  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RUNTIMES = ("compiled", "numpy")
PACKAGE = "src/latentsim/runtime"  # the runtime package; before the layout by domain, two flat modules:
FLAT = {"__init__.py": "src/latentsim/runtime.py", "compiled.py": "src/latentsim/runtime_compiled.py"}
REV = "latentsim._runtime_rev"  # the revision's package, beside the working tree's


def current_module(kind: str = "numpy"):
    """The working tree's runtime module of that kind."""
    if kind == "compiled":
        if not current_compiled.available():
            raise SystemExit("--runtime compiled needs numba (pinned in envs/requirements.txt)")
        return current_compiled
    return current


def _git(root: Path, *args) -> str:
    try:
        return subprocess.run(["git", *args], cwd=root, check=True, capture_output=True, text=True).stdout
    except subprocess.CalledProcessError as e:
        raise SystemExit(f"git {' '.join(args)} failed: {e.stderr.strip()}") from e


def _revision_sources(rev: str, root: Path) -> dict:
    """{file name in the package: source} of the runtime at ``rev``, its imports of itself redirected to REV."""
    listed = _git(root, "ls-tree", "--name-only", rev, f"{PACKAGE}/").split()
    paths = {Path(p).name: p for p in listed if p.endswith(".py")} or FLAT
    out = {}
    for name, path in paths.items():
        text = _git(root, "show", f"{rev}:{path}")
        text = re.sub(r"\blatentsim\.runtime_compiled\b", f"{REV}.compiled", text)
        out[name] = re.sub(r"\blatentsim\.runtime\b", REV, text)
    return out


def load_revision(rev: str, root: Path = ROOT, kind: str = "numpy"):
    """The runtime module of that kind (``latentsim.runtime`` or ``latentsim.runtime.compiled``) as it was at git
    revision ``rev``, as a separate package ``latentsim._runtime_rev`` (written to a temporary folder)."""
    folder = Path(tempfile.mkdtemp()) / "_runtime_rev"
    folder.mkdir()
    for name, text in _revision_sources(rev, root).items():
        (folder / name).write_text(text)
    for name in [m for m in sys.modules if m == REV or m.startswith(REV + ".")]:  # an earlier revision's
        del sys.modules[name]
    spec = importlib.util.spec_from_file_location(REV, folder / "__init__.py", submodule_search_locations=[str(folder)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[REV] = module
    spec.loader.exec_module(module)
    return importlib.import_module(f"{REV}.compiled") if kind == "compiled" else module


def _median_us(fn, repeats: int) -> float:
    """Median wall time [us] of ``fn()`` (``runtime.time_jvp`` times any callable)."""
    return 1e3 * current.time_jvp(fn, repeats=repeats, warmup=100)


def _framed(module, stepper):
    """``stepper`` inside its revision's ``RigidFrameStepper`` (``module``'s package) where its file was encoded in a
    rigid frame (``autoencoder.rigid_frame``: header ``rigid_frame``), as a loaded model steps it; else itself."""
    frame = stepper.header.get("rigid_frame")
    if frame is None:
        return stepper
    package = sys.modules[module.__name__.rsplit(".compiled", 1)[0]]
    return package.RigidFrameStepper(stepper, frame["vertices"], frame["rest_frame"])


def compare(npz, old, new=current, rounds: int = 5, repeats: int = 1000, seed: int = 0) -> dict:
    """Time one step of the runtime file ``npz`` with modules ``old`` and ``new``, alternating (a file of a rigid
    frame: each inside its revision's ``RigidFrameStepper``, finding the frame and carrying the positions out)."""
    a, b = _framed(old, old.load_runtime(npz)), _framed(new, new.load_runtime(npz))
    rng = np.random.default_rng(seed)
    z = (0.1 * rng.standard_normal(b.r)).astype(np.float32)
    p = rng.standard_normal(b.k).astype(np.float32)
    xD = np.ascontiguousarray(rng.standard_normal((len(b.dirichlet), 3)))  # an older compiled stepper may not list them
    xa = a.step(z, z, p, p, p, xD)[1].copy()
    xb = b.step(z, z, p, p, p, xD)[1].copy()
    ta, tb = [], []
    for _ in range(rounds):
        ta.append(_median_us(lambda: a.step(z, z, p, p, p, xD), repeats))
        tb.append(_median_us(lambda: b.step(z, z, p, p, p, xD), repeats))
    old_us, new_us = float(np.median(ta)), float(np.median(tb))
    mode = b.mode + (" (rigid frame)" if "rigid_frame" in b.header else "")
    return {"mode": mode, "layout": getattr(b, "layout", "-"), "old_us": old_us, "new_us": new_us,
            "speedup": old_us / new_us, "max_dx": float(np.abs(xa - xb).max())}  # fmt: skip


def main(argv=None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--against", required=True, help="git revision whose runtime is the baseline")
    ap.add_argument("--results", default="results", help="the pipeline's results folder")
    ap.add_argument("--method", default="self_supervised")
    ap.add_argument("--seed", type=int, default=0, help="the seed of the trained runtimes (default: %(default)s)")
    ap.add_argument("--scenes", nargs="*", help="default: every scene with a runtime file")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=1000)
    ap.add_argument("--runtime", choices=RUNTIMES, default="numpy", help="which runtime module to compare")
    ap.add_argument("--npz", nargs="+", type=Path, help="runtime files to time instead of the pipeline's (named by their stem)")
    args = ap.parse_args(argv)
    if args.npz:
        files = {p.stem: p for p in args.npz}
    else:
        base, seed = Path(args.results) / "rollout", seed_dir(args.seed)
        scenes = args.scenes or sorted(p.parents[2].name for p in base.glob(f"*/{args.method}/{seed}/runtime.npz"))
        if not scenes:
            raise SystemExit(f"no {base}/<scene>/{args.method}/{seed}/runtime.npz: run the rollout stage first")
        files = {scene: base / scene / args.method / seed / "runtime.npz" for scene in scenes}
    old, new = load_revision(args.against, kind=args.runtime), current_module(args.runtime)
    rows = []
    for scene, npz in files.items():
        if not npz.exists():
            raise SystemExit(f"{npz}: no such runtime file")
        rows.append({"scene": scene, **compare(npz, old, new, rounds=args.rounds, repeats=args.repeats)})
        print(f"{scene}: {rows[-1]}", file=sys.stderr)
    df = pd.DataFrame(rows)
    print(f"one step, us, {args.runtime} runtime (median of {args.rounds} alternating rounds of {args.repeats}); old = {args.against}")
    print(df.to_markdown(index=False, floatfmt=".3g"))
    return df


if __name__ == "__main__":
    main()

"""The floor of a latent step against a full-space frame: can any network reach 1000x on a scene?

    python benchmarks/bench_step_floor.py cloth hair_rotation hair_translation bunny_ears armadillo \\
        [--results results] [--config config/config.yaml] [--latent 2] [--width 8] [--export DIR]

For each scene, from its simulated trajectories (``<results>/sim/<scene>/trajectories.h5``; run
``snakemake --cores 2 results/sim/<scene>/trajectories.h5`` first), an untrained network far smaller
than any scene needs (latent ``--latent``, one hidden layer of ``--width`` in the integrator; the
decoder's branch is untrained, its output layer zero, so the runtime folds it to a linear decoder of
``--latent`` columns; the coordinates of the scene's config): its step still decodes every DoF
through the output layer, so its time is a floor under every trained model's step on that mesh.
Timed in the same process as full-space Newton frames of the scene's first test sequence (``latent.timing.time_full_space``, as the rollout
stage times them), in interleaved rounds, one thread. Prints the full-space ms, the floor step in us,
the floor's speed-up, and the step a 1000x speed-up would need, for the NumPy runtime and the compiled
one (``latentsim.runtime.compiled``, one numba kernel call per step).

Below both (at ``--latent 2``, the default and the smallest latent any scene uses), ``bare``: a latent-2
linear decoder's arithmetic alone, ``x = A[2] + z_0 A[0] + z_1 A[1]`` over every DoF in one compiled pass
(float32 weights, float64 positions; no integrator, no origins, no prescribed vertices, one call). A step
that decodes the scene's DoF from a latent of 2 or more does at least this work, so ``bare_floor_speedup``
bounds what any such network can reach on this machine.
"""

from __future__ import annotations

import argparse
import os
from functools import partial

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import h5py  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import torch  # noqa: E402

from latentsim import runtime  # noqa: E402
from latentsim.runtime import compiled as runtime_compiled
from latentsim.config import load_config  # noqa: E402
from latentsim.latent import Autoencoder, LatentIntegrator  # noqa: E402
from latentsim.latent import coordinates_for, load_sequences  # noqa: E402
from latentsim.latent.timing import time_full_space  # noqa: E402


if runtime_compiled.available():  # numba is pinned; without it the bare bound is not printed
    from numba import njit

    @njit(boundscheck=False, fastmath={"reassoc", "contract", "arcp", "nsz", "afn"}, cache=True)
    def _bare_decode(A, z, x):
        """x[:] = A[2] + z[0] A[0] + z[1] A[1]: a latent-2 linear decoder's arithmetic and memory traffic in one
        pass over contiguous rows (it vectorises), nothing else."""
        a0, a1, b = A[0], A[1], A[2]
        z0, z1 = z[0], z[1]
        for j in range(x.shape[0]):
            x[j] = b[j] + z0 * a0[j] + z1 * a1[j]


def time_bare_ms(dof: int, repeats: int, seed: int = 0) -> float:
    """Median ms of :func:`_bare_decode` on ``dof`` outputs, one call at a time (``runtime.time_jvp``)."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((3, dof)).astype(np.float32)
    z, x = rng.standard_normal(2).astype(np.float32), np.empty(dof)
    return runtime.time_jvp(partial(_bare_decode, A, z, x), repeats=repeats)  # partial: no Python frame per call


def floor_stepper(f, latent: int, width: int, coordinates=None, seed: int = 0, export=None):
    """Steppers (NumPy, and compiled where numba imports) of a minimal untrained autoencoder + integrator on the scene of the open trajectories.h5
    (``coordinates``: the autoencoder's, as the config's ``autoencoder.coordinates``); ``export``: also write it as
    a runtime file there (``runtime.export_runtime``), for ``bench_runtime_ab.py --npz``."""
    torch.manual_seed(seed)
    coords = coordinates_for(f, coordinates)
    test = load_sequences(f, "test")
    name, seq = next(iter(test.items()))
    ae = Autoencoder(coords.dim, latent, [width], None).eval()
    integ = LatentIntegrator(latent, np.asarray(seq["bc"]).shape[-1], [width]).eval()
    if export is not None:
        runtime.export_runtime(ae, integ, coords, export)
    return runtime_compiled.deployable_steppers(runtime.fold_networks(ae, integ, coords)), name, seq, coords.mode


def bench(path, latent: int, width: int, rounds: int, frames: int, repeats: int, coordinates=None, export=None) -> dict:
    """Full-space ms and each runtime's floor step (us) and speed-up, medians of interleaved rounds."""
    with h5py.File(path, "r") as f:
        steppers, name, seq, mode = floor_stepper(f, latent, width, coordinates, export=export)
        dof = int(f["rest_positions"].size)
        z = np.zeros(latent, np.float32)
        p = np.asarray(seq["bc"][-1], np.float32)
        xD = np.ascontiguousarray(seq["dirichlet_positions"][-1], np.float64)
        full, step = [], {k: [] for k in steppers}
        if runtime_compiled.available() and latent == 2:
            step["bare"] = []
        for _ in range(rounds):
            full.append(time_full_space(f, name, frames)["full_ms"])
            for k, st in steppers.items():
                step[k].append(runtime.time_step(st, z, z, p, p, p, xD, repeats=repeats)["step_ms"])
            if "bare" in step:
                step["bare"].append(time_bare_ms(dof, repeats))
    full_ms = float(np.median(full))
    row = {"coordinates": mode, "dof": dof, "sequence": name, "full_ms": full_ms, "step_for_1000x_us": full_ms}  # full_ms / 1000 in us
    for k, s in step.items():
        step_ms = float(np.median(s))
        row[f"{k}_floor_us"] = 1e3 * step_ms
        row[f"{k}_floor_speedup"] = full_ms / step_ms
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--results", default="results")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--latent", type=int, default=2)
    ap.add_argument("--width", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--full-frames", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=500)
    ap.add_argument("--export", metavar="DIR", help="also write each scene's floor network as DIR/<scene>.npz")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cfg = load_config(args.config)
    rows = []
    for scene in args.scenes:
        path = os.path.join(args.results, "sim", scene, "trajectories.h5")
        if not os.path.exists(path):
            raise SystemExit(f"{path}: missing; run `snakemake --cores 2 {path}` first")
        if scene not in cfg["scenes"]:
            raise SystemExit(f"{args.config}: no scene '{scene}'")
        coordinates = cfg["scenes"][scene]["autoencoder"].get("coordinates")
        export = os.path.join(args.export, f"{scene}.npz") if args.export else None
        row = bench(path, args.latent, args.width, args.rounds, args.full_frames, args.repeats, coordinates, export)
        rows.append({"scene": scene, **row})
        print(pd.DataFrame(rows[-1:]).to_string(index=False, float_format=lambda v: f"{v:.4g}"), flush=True)
    print(f"\nlatent {args.latent}, a linear decoder, one hidden layer of {args.width} in the integrator, medians of {args.rounds} rounds:")
    print(pd.DataFrame(rows).to_markdown(index=False, floatfmt=".4g"))


if __name__ == "__main__":
    main()

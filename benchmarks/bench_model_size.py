"""One model size of a scene, trained, measured and timed against the full space in one process.

    python benchmarks/bench_model_size.py armadillo --latent 8 --autoencoder 64 64 --integrator 64 64 \\
        --variant hybrid_w1e4 --against results/rollout/armadillo/self_supervised/seed0/runtime.npz

Trains the scene's autoencoder and integrator at the given sizes (the integrator with the loss of
``--variant``, or the paper's self-supervised loss without it) on ``results/sim/<scene>/trajectories.h5``
exactly as a sizing-sweep point does (``sweep.train_point``, the scene's first seed), measures it as the
sweep does (``sweep.measure_point``: mean and max vertex error over the bounding-box diagonal on every
test sequence, the stress conditions), then times, in interleaved rounds and on one thread, full-space
Newton frames of the first test sequence (``latent.timing.time_full_space``, as the rollout stage does), its
NumPy step, and the step of each ``--against`` runtime (e.g. the pipeline's paper-size network), and
prints the speed-ups of the same process.  Training the armadillo takes about 11 minutes on one core.
"""

import argparse
import os

os.environ.setdefault("MKL_NUM_THREADS", "1")  # the full-space frames on one thread, as in the pipeline's jobs
os.environ.setdefault("OMP_NUM_THREADS", "1")

import h5py  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from latentsim import runtime  # noqa: E402
from latentsim.config import integrator_settings, load_config, scene_seeds  # noqa: E402
from latentsim.stages.sweep import measure_point, train_point  # noqa: E402
from latentsim.latent.timing import time_full_space  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--results", default="results")
    ap.add_argument("--latent", type=int, required=True)
    ap.add_argument("--autoencoder", type=int, nargs="+", required=True, help="autoencoder hidden widths")
    ap.add_argument("--integrator", type=int, nargs="+", required=True, help="integrator hidden widths")
    ap.add_argument("--variant", default="self_supervised", help="the integrator's loss: self_supervised or a config variant")
    ap.add_argument("--against", nargs="*", default=[], help="runtime.npz files to time beside it")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--full-frames", type=int, default=20)
    ap.add_argument("--no-stress", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)

    cfg = load_config(args.config)
    if args.scene not in cfg["scenes"]:
        raise SystemExit(f"{args.config}: no scene '{args.scene}'")
    sc = cfg["scenes"][args.scene]
    traj = os.path.join(args.results, "sim", args.scene, "trajectories.h5")
    if not os.path.exists(traj):
        raise SystemExit(f"{traj}: missing; run `snakemake --cores 2 {traj}` first")
    ae_cfg = dict(sc["autoencoder"], latent_dim=args.latent, widths=args.autoencoder)
    integ_cfg = dict(integrator_settings(cfg, args.scene, args.variant), widths=args.integrator)

    point = train_point(traj, ae_cfg, integ_cfg, scene_seeds(cfg, args.scene)[0])
    print(f"{args.scene}, latent {args.latent}, {args.autoencoder} / {args.integrator}, {args.variant}: trained in "
          f"{point['train_seconds']:.0f} s")  # fmt: skip
    df = measure_point(point, sc["rollout"], stress=not args.no_stress)
    cols = ["sequence", "frames", "diverged_frame", "mean_error", "max_error", "step_ms", "stress_conditions", "stress_failed", "stress_failures"]
    print(df[cols].to_markdown(index=False))

    steppers = {"this size": (runtime.NumpyStepper(runtime.fold_networks(point["ae"], point["integrator"], point["coords"])), args.latent)}
    for path in args.against:
        st = runtime.load_runtime(path)
        steppers[path] = (st, st.r)
    seq = next(iter(point["tests"]))
    s = point["tests"][seq]
    xD = np.asarray(s["dirichlet_positions"][-1], np.float64)
    p = np.asarray(s["bc"][-1], np.float32)
    rows = []
    for rnd in range(args.rounds):
        with h5py.File(traj, "r") as f:
            full = time_full_space(f, seq, args.full_frames)["full_ms"]
        row = {"round": rnd, "full_ms": full}
        for name, (st, r) in steppers.items():
            z = np.zeros(r, np.float32)
            row[name] = runtime.time_step(st, z, z, p, p, p, xD, repeats=int(sc["rollout"]["timing_repeats"]))["step_ms"]
        rows.append(row)
        print(f"round {rnd}: full {full:.1f} ms; " + "; ".join(f"{n} {1e3 * row[n]:.1f} us ({full / row[n]:.0f}x)" for n in steppers))
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0] if k != "round"}
    print(f"median: full {med['full_ms']:.1f} ms; " + "; ".join(f"{n} {1e3 * med[n]:.1f} us ({med['full_ms'] / med[n]:.0f}x)" for n in steppers))


if __name__ == "__main__":
    main()

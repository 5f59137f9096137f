"""Li et al. 2025 Table 2, honestly: the cost of one latent step against a single-vertex Jvp
and against a whole Fulton-style reduced implicit-Euler step.

For every Li et al. scene, at our mesh's DoF count and with the paper's network sizes
(Table 2: decoder and integrator layers; Table 1: latent dimension), random weights (no
trained model needed; ``--networks trained`` takes the pipeline's ``results/`` models of seed ``--seed``,
``results/autoencoder/{scene}/seed{k}/`` and ``results/integrator/{scene}/self_supervised/seed{k}/``):

- Jvp of one decoded vertex w.r.t. the latent: as the paper did (``torch.func.jvp`` of the
  eager decoder, restricted to the vertex), the same on the folded layers (BatchNorm folded,
  eager), and by hand-written forward mode through the folded NumPy layers (only the
  vertex's 3 output rows of the last layer);
- one whole latent step (integration + decoding to every vertex): the NumPy runtime
  (float32, preallocated), the folded step exported with ``torch.export`` (float32), and eager PyTorch;
- one reduced implicit-Euler step in the autoencoder's latent space (Fulton et al. 2019,
  every element, every Gauss-Newton iteration to the scene's Newton tolerance), from rest
  under the scene's first boundary-condition program.

    python benchmarks/bench_latent_step.py [--scenes cloth armadillo] [--repeats 300]
    python benchmarks/bench_latent_step.py --markdown results/benchmarks/latent_step.md

Medians of repeated single-frame timings, one thread (``--threads``); the machine is shared,
so compare columns of one run.  Two readings of the paper's decoder layers are benchmarked
(``--readings``, see :func:`autoencoder_shape`): the pipeline config's (PCA layer as wide as the
first width) and the printed order with the PCA coefficients last.  The random decoder spans a PCA-like subspace of smooth
random displacements around the rest shape, so the reduced step's iteration count is that of
a plausible but untrained subspace; with ``--networks trained`` it is the trained one's.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path


def _threads_from_argv(default: int = 1) -> int:
    for i, a in enumerate(sys.argv):
        if a == "--threads" and i + 1 < len(sys.argv):
            return int(sys.argv[i + 1])
        if a.startswith("--threads="):
            return int(a.split("=", 1)[1])
    return default


# BLAS pools must be sized before numpy/torch start them
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = str(_threads_from_argv())

import numpy as np
import pandas as pd
import torch

from latentsim import runtime as rt
from latentsim.config import autoencoder_dir, load_config, seed_dir
from latentsim.latent import (
    Autoencoder,
    LatentIntegrator,
    RelativeCoordinates,
    load_autoencoder,
    load_integrator,
)
from latentsim.report.metrics import bbox_diagonal
from latentsim.report.paper import LI2025_TABLE1, LI2025_TABLE2
from latentsim.stages.mesh import prepare_mesh
from latentsim.latent.subspaces import DecoderSubspace
from latentsim.latent.timing import EagerStepper
from latentsim.solve.reduced import (
    ReducedImplicitEuler,
    ReducedSettings,
    reduced_rollout,
)
from latentsim.scene import BC_DIM, bc_parameters, build_potential, dirichlet_trajectory
from latentsim.io import read_mesh_arrays

ROOT = Path(__file__).resolve().parents[1]


def _layers(text: str) -> list[int]:
    return [int(w) for w in text.split(",")]


def scene_arrays(name, sc, meshes):
    """Mesh arrays of a scene: results/mesh/{scene}/mesh.h5 when the pipeline made it, else built here."""
    path = ROOT / "results" / "mesh" / name / "mesh.h5"
    if path.exists():
        return read_mesh_arrays(path)
    with tempfile.TemporaryDirectory() as tmp:
        prepare_mesh(name, sc["model"], sc["mesh"], sc["dirichlet"], meshes, Path(tmp) / "mesh.h5")
        return read_mesh_arrays(Path(tmp) / "mesh.h5")


def coordinates(model, arrays):
    n = len(arrays["rest_positions"])
    if model == "rods":
        return RelativeCoordinates(n, arrays["dirichlet"], "roots", root_of=arrays["root_of"])
    return RelativeCoordinates(n, arrays["dirichlet"], "mean")


def smooth_fields(rest, degree: int) -> np.ndarray:
    """(n, F) monomials c_x^a c_y^b c_z^c, a + b + c <= degree, of the rest coordinates scaled to [-1, 1]."""
    c = 2.0 * (rest - rest.min(0)) / np.maximum(np.ptp(rest, axis=0), 1e-9) - 1.0
    cols, degs = [], []
    for a in range(degree + 1):
        for b in range(degree + 1 - a):
            for k in range(degree + 1 - a - b):
                cols.append(c[:, 0] ** a * c[:, 1] ** b * c[:, 2] ** k)
                degs.append(a + b + k)
    return np.stack(cols, 1), np.asarray(degs)


def autoencoder_shape(layers: list[int], reading: str):
    """(widths, pca_dim) of :class:`Autoencoder` for the paper's decoder layers, e.g. 200, 200, 200, 50.

    ``config``: as the pipeline's config reads them, ``widths = layers`` and the PCA layer as wide
    as ``widths[0]`` (decoder r -> 50 -> 200 -> 200 -> 200 -> 200 (PCA) -> d).  ``pca-last``: the
    decoder in the order printed, its last layer the PCA coefficients (r -> 200 -> 200 -> 200 ->
    50 (PCA) -> d), the Fulton et al. layout.
    """
    if reading == "config":
        return layers, None
    return layers[:-1], layers[-1]


def paper_networks(coords, rest, latent_dim, dec_widths, int_widths, seed=0, pca_dim=None):
    """Paper-sized autoencoder and integrator with random weights.

    The PCA layers come from synthetic frames: the rest shape plus smooth random displacement
    fields (random combinations of the monomials of the rest coordinates up to the degree that
    gives enough independent fields, amplitudes falling with the degree, a few percent of the
    bounding-box diagonal at degree 1), so the decoder maps the latent to smooth deformations;
    the residual branch and BatchNorm statistics are randomised so the map is nonlinear.
    """
    g = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    ae = Autoencoder(coords.dim, latent_dim, dec_widths, pca_dim)
    p = ae.pca_dim
    degree = 1
    while 3 * smooth_fields(rest[:1], degree)[0].shape[1] < p + 8:
        degree += 1
    Phi, degs = smooth_fields(rest, degree)
    diag = bbox_diagonal(rest)
    N = p + 32
    amp = 0.03 * diag / np.maximum(degs, 1.0) ** 2
    coef = rng.standard_normal((N, Phi.shape[1], 3)) * amp[None, :, None]
    frames = rest[None] + np.einsum("nf,bfk->bnk", Phi, coef)
    xD = torch.as_tensor(rest[coords.dirichlet.numpy()])
    U = coords.encode(torch.as_tensor(frames), xD.expand(N, -1, -1))
    ae.init_pca(U)
    with torch.no_grad():
        ae.dec_branch.out.weight.normal_(0.0, 0.005, generator=g)
        for branch in (ae.enc_branch, ae.dec_branch):
            for blk in branch.blocks:
                blk[1].running_mean.normal_(0.0, 0.1, generator=g)
                blk[1].running_var.uniform_(0.5, 2.0, generator=g)
    integ = LatentIntegrator(latent_dim, BC_DIM, int_widths)
    return ae.eval(), integ.eval()


def bench_scene(name, sc, cfg, args, reading):
    arrays = scene_arrays(name, sc, cfg["meshes"])
    rest = np.asarray(arrays["rest_positions"], dtype=np.float64)
    coords = coordinates(sc["model"], arrays)
    dec_text, int_text, paper_jvp, paper_total = LI2025_TABLE2[name]
    r = LI2025_TABLE1[name][1]
    if args.networks == "trained":
        ae = load_autoencoder(ROOT / autoencoder_dir(cfg, name, "self_supervised", args.seed) / "autoencoder.pt")
        integ = load_integrator(ROOT / "results" / "integrator" / name / "self_supervised" / seed_dir(args.seed) / "integrator.pt")
        r = ae.latent_dim
        dec_text = ", ".join(str(w) for w in ae.hparams["widths"])
        int_text = ", ".join(str(w) for w in integ.hparams["widths"])
    else:
        widths, pca_dim = autoencoder_shape(_layers(dec_text), reading)
        ae, integ = paper_networks(coords, rest, r, widths, _layers(int_text), seed=args.seed, pca_dim=pca_dim)
    folded = rt.fold_networks(ae, integ, coords)

    # inputs of one frame
    rng = np.random.default_rng(args.seed)
    D = np.asarray(arrays["dirichlet"])
    z1, z2 = (rng.standard_normal(r).astype(np.float32) for _ in range(2))
    p = rng.standard_normal(BC_DIM).astype(np.float32)
    xD = np.ascontiguousarray(rest[D])
    np_step = rt.NumpyStepper(folded, np.float32)
    t_np = rt.time_step(np_step, z1, z2, p, p, p, xD, repeats=args.repeats)
    t_export = rt.time_step(rt.ExportedStepper(folded), z1, z2, p, p, p, xD, repeats=args.repeats)
    t_eager = rt.time_step(EagerStepper(ae, integ, coords), z1, z2, p, p, p, xD, repeats=args.repeats)

    # single-vertex Jvp: the vertex furthest from the Dirichlet set's centroid (a free one)
    enc = coords.encoded_vertices.numpy()
    vertex = int(enc[np.argmax(np.linalg.norm(rest[enc] - rest[D].mean(0), axis=1))])
    row = int(np.flatnonzero(enc == vertex)[0])
    zt, vt = torch.from_numpy(z1), torch.from_numpy(rng.standard_normal(r).astype(np.float32))
    jvp_torch = rt.time_jvp(lambda: rt.jvp_vertex_torch(ae, zt, vt, row), repeats=args.jvp_repeats)
    folded_eager = rt.FoldedStep(folded).eval()  # the folded layers as a plain (eager) module
    xDt = torch.from_numpy(xD)
    jvp_folded = rt.time_jvp(
        lambda: torch.func.jvp(lambda zz: folded_eager.decoder(zz, xDt)[vertex], (zt,), (vt,)), repeats=args.jvp_repeats
    )
    jvp_fwd = rt.time_jvp(lambda: np_step.jvp_vertex(z1, vt.numpy(), vertex), repeats=args.repeats)
    du_ref = rt.jvp_vertex_torch(ae, zt, vt, row)[1]
    du = np_step.jvp_vertex(z1, vt.numpy(), vertex)[1]
    jvp_err = float(np.abs(du - du_ref.detach().numpy()).max() / max(np.abs(du_ref.detach().numpy()).max(), 1e-30))

    # Fulton-style reduced implicit Euler in the decoder's latent space, from rest
    pot = build_potential(sc["model"], arrays, sc["material"], sc["dt"], sc["gravity"])  # every stencil
    sub = DecoderSubspace(ae, coords)
    T = 2 + args.reduced_warmup + args.reduced_frames
    seq = sc["sequences"][0]
    xD_t = dirichlet_trajectory(rest[D], bc_parameters(seq, T), sc["dt"])
    q0 = sub.project(rest, xD_t[0])
    settings = ReducedSettings(tolerance=float(sc["newton"]["tolerance"]), max_iterations=args.reduced_max_iterations)
    try:  # the full-space solver's compiled kernels where it has them (its default), or not
        solver = ReducedImplicitEuler(sub, pot, settings, {} if args.kernels == "auto" else {"kernels": False})
    except TypeError:  # a solver without the kernel option
        solver = ReducedImplicitEuler(sub, pot, settings)
    derivatives = "kernels" if getattr(solver.inner, "kernels", None) is not None else "reference"
    t0 = time.perf_counter()
    red = reduced_rollout(sub, pot, q0, q0, xD_t, solver=solver)
    red_wall = time.perf_counter() - t0
    timed = slice(2 + args.reduced_warmup, T)
    ms = red["step_ms"][timed]
    its = red["iterations"][timed]
    ok = red["diverged_frame"] < 0
    red_ms = float(np.nanmedian(ms)) if ok else float("nan")
    red_it = float(np.mean(its)) if ok else float("nan")
    return {
        "scene": name,
        "DoF (paper)": LI2025_TABLE1[name][0],
        "DoF (ours)": int(rest.size),
        "r": r,
        "decoder layers": dec_text,
        "reading": reading if args.networks == "paper" else "trained",
        "PCA dim": int(ae.pca_dim),
        "integrator layers": int_text,
        "paper Jvp ms": paper_jvp,
        "torch.func.jvp ms": jvp_torch,
        "torch.func.jvp folded ms": jvp_folded,
        "forward-mode Jvp ms": jvp_fwd,
        "Jvp rel. diff": jvp_err,
        "paper step ms": paper_total,
        "NumPy step ms": t_np["step_ms"],
        "NumPy integrate ms": t_np["integrate_ms"],
        "NumPy decode ms": t_np["decode_ms"],
        "torch.export step ms": t_export["step_ms"],
        "eager step ms": t_eager["step_ms"],
        "reduced derivatives": derivatives,
        "reduced step ms": red_ms,
        "reduced it/step": red_it,
        # per evaluation of the map, its Jacobian and the full-space derivatives: iterations + 1
        # per step (the last one only tests convergence)
        "reduced ms/eval": float(np.nansum(ms) / np.sum(its + 1)) if ok else float("nan"),
        **{f"reduced {k} ms/eval": (float(np.nansum(red[f"{k}_ms"][timed]) / np.sum(its + 1)) if ok else float("nan"))
           for k in ("map", "derivatives", "reduce", "line_search")},
        "reduced / NumPy step": red_ms / t_np["step_ms"],
        "torch.func.jvp / NumPy step": jvp_torch / t_np["step_ms"],
        "reduced failed at": int(red["diverged_frame"]),
        "reduced wall s": red_wall,
    }


def _markdown(df: pd.DataFrame) -> str:
    def fmt(v):
        if isinstance(v, float):
            if not np.isfinite(v):
                return "nan"
            return f"{v:.3g}" if abs(v) < 100 else f"{v:,.0f}"
        return f"{v:,}" if isinstance(v, int) else str(v)

    head = "| " + " | ".join(df.columns) + " |\n|" + "---|" * len(df.columns) + "\n"
    return head + "".join("| " + " | ".join(fmt(v) for v in row) + " |\n" for row in df.itertuples(index=False))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--scenes", nargs="*", default=list(LI2025_TABLE2))
    ap.add_argument("--networks", choices=["paper", "trained"], default="paper")
    ap.add_argument("--readings", nargs="+", choices=["config", "pca-last"], default=["config", "pca-last"],
                    help="how the paper's decoder layers map to the autoencoder (see autoencoder_shape)")
    ap.add_argument("--repeats", type=int, default=300, help="timed repetitions of each latent-step and Jvp timing")
    ap.add_argument("--jvp-repeats", type=int, default=100, help="repetitions of the torch.func.jvp timing")
    ap.add_argument("--reduced-frames", type=int, default=5, help="reduced steps timed")
    ap.add_argument("--reduced-warmup", type=int, default=2, help="reduced steps from rest not timed")
    ap.add_argument("--reduced-max-iterations", type=int, default=50)
    ap.add_argument("--kernels", choices=["auto", "off"], default="auto",
                    help="full-space gradients/Hessians of the reduced step: the solver's compiled kernels where it has them, or its reference path")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0,
                    help="the random networks' and inputs' seed; with --networks trained, also the seed of the trained models")
    ap.add_argument("--markdown", help="also write the table to this file")
    ap.add_argument("--csv", help="also write the table to this CSV file")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    rows = []
    for name in args.scenes:
        sc = cfg["scenes"][name]
        for reading in args.readings if args.networks == "paper" else ["trained"]:
            t0 = time.perf_counter()
            try:
                rows.append(bench_scene(name, sc, cfg, args, reading))
            except FileNotFoundError:
                print(f"# {name}: no trained model of seed {args.seed} in results/, skipped", file=sys.stderr, flush=True)
                continue
            print(f"# {name} ({reading}): {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    df = pd.DataFrame(rows)
    text = _markdown(df)
    print(text)
    if args.markdown:
        Path(args.markdown).parent.mkdir(parents=True, exist_ok=True)
        Path(args.markdown).write_text(text)
    if args.csv:
        Path(args.csv).parent.mkdir(parents=True, exist_ok=True)
        df.to_csv(args.csv, index=False)


if __name__ == "__main__":
    main()

"""Where a latent integrator's one-step predictions sit against its loss's own optimum.

For every frame t of a scene's test sequences, from the ground-truth latents of t-1 and t-2 (the
autoencoder's encodings), compare three latents with the ground-truth latent z_t (the models of seed
``--seed``, default 0: ``results/autoencoder/{scene}/seed{k}/``, ``results/integrator/{scene}/{method}/seed{k}/``):

- each integrator's one-step prediction I(z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2});
- the minimiser of the self-supervised loss itself, the incremental potential of the decoded state
  (L-BFGS in the latent space from z_t): the best that training on Eq. 4 can reach on this decoder.

Printed per frame range: mean vertex distance between each decoded latent and the decoded z_t (a
fraction of the rest bounding-box diagonal), and the incremental potential minus that of z_t.  A
prediction far from z_t while the minimiser lies near it means the integrator misses its own loss's
optimum (a fitting or generalisation error); a minimiser far from z_t means the loss is biased on
this decoder.

    python benchmarks/integrator_optimum.py hair_translation --methods self_supervised supervised_5x256 \\
        --ranges 2 100 300 [--seed 1]     # run in a working directory whose results/ hold the scene's stages
"""

from __future__ import annotations

import argparse
from pathlib import Path

import h5py
import torch

from latentsim import latent
from latentsim.config import seed_dir
from latentsim.report.metrics import bbox_diagonal
from latentsim.scene import potential_from_artefact
from latentsim.latent import autoencoder_coordinates, load_sequences


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--results", default="results")
    ap.add_argument("--methods", nargs="+", default=["self_supervised"])
    ap.add_argument("--seed", type=int, default=0, help="the seed of the trained models (default: %(default)s)")
    ap.add_argument("--ranges", nargs="+", type=int, default=[2, 100, 300], help="frame boundaries of the rows")
    ap.add_argument("--lbfgs-steps", type=int, default=5, help="L-BFGS steps (200 iterations each) for the minimiser")
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    res = Path(args.results)
    ae_path = res / "autoencoder" / args.scene / seed_dir(args.seed) / "autoencoder.pt"
    with h5py.File(res / "sim" / args.scene / "trajectories.h5", "r") as f:
        coords = autoencoder_coordinates(f, ae_path)
        test = load_sequences(f, "test")
        pot = potential_from_artefact(f)
        diag = bbox_diagonal(f["rest_positions"][()])
    ae = latent.load_autoencoder(ae_path).double()
    b = {k: v.double() for k, v in latent.build_triplets(ae, coords, list(test.values())).items()}
    with torch.no_grad():
        x1 = latent.decode_latents(ae, coords, b["z_prev"], b["xD_prev"])
        x2 = latent.decode_latents(ae, coords, b["z_prev2"], b["xD_prev2"])
        x_gt = latent.decode_latents(ae, coords, b["z"], b["xD"])

    def potential(z):
        return pot(latent.decode_latents(ae, coords, z, b["xD"]), x1, x2, targets=b["xD"], penalty=False)

    latents = {}
    with torch.no_grad():
        for m in args.methods:
            integ = latent.load_integrator(res / "integrator" / args.scene / m / seed_dir(args.seed) / "integrator.pt").double()
            latents[f"{m}, one step"] = integ(b["z_prev"], b["z_prev2"], b["p"], b["p_prev"], b["p_prev2"])
    z = b["z"].clone().requires_grad_(True)
    opt = torch.optim.LBFGS([z], max_iter=200, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = potential(z).sum()
        loss.backward()
        return loss

    for _ in range(args.lbfgs_steps):
        opt.step(closure)
    latents["minimiser of the loss"] = z.detach()
    with torch.no_grad():
        e_gt = potential(b["z"]).numpy()
        print(f"{args.scene}: {len(e_gt)} test triplets (frames 2.. of each test sequence, concatenated)")
        print("| latent | frames | vertex distance to z_t / diagonal | potential - potential(z_t) | potential(z_t) |")
        print("|---|---|---|---|---|")
        for name, zz in latents.items():
            dist = ((latent.decode_latents(ae, coords, zz, b["xD"]) - x_gt).norm(dim=-1).mean(-1) / diag).numpy()
            de = potential(zz).numpy() - e_gt
            for lo, hi in zip(args.ranges[:-1], args.ranges[1:]):
                s = slice(lo - 2, hi - 2)
                print(f"| {name} | {lo}-{hi} | {dist[s].mean():.4f} | {de[s].mean():.3e} | {e_gt[s].mean():.3e} |")


if __name__ == "__main__":
    main()

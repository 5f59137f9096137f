"""Where StVK fails and stable neo-Hookean does not: a tet scene's test sequence at several Young's moduli.

For each modulus and material model, the scene's first test sequence is simulated with the pipeline's
own mesh, potential and Newton (``latentsim.stages.simulate.simulate_sequence``), and the table gives the
frames solved, the frame where Newton failed (if it did), the frames that end with an inverted tet and
the smallest det F seen.

    python benchmarks/soft_solids.py --scene armadillo --moduli 1e6 3e5 --frames 700
    python benchmarks/soft_solids.py --scene nm_giraffe --moduli 1e7 1e6
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from latentsim.config import load_config
from latentsim.mesh import scene_mesh
from latentsim.scene import build_potential
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings
from latentsim.stages.simulate import SimulationError, simulate_sequence, volume_ratios


def run(cfg: dict, scene: str, arrays: dict, modulus: float, law: str, frames: int | None) -> dict:
    sc = cfg["scenes"][scene]
    material = dict(sc["material"], youngs_modulus=float(modulus), model=law)
    seq = next(s for s in sc["sequences"] if s.get("split") == "test")
    if frames:
        seq = dict(seq, frames=min(int(seq["frames"]), frames))
    pot = build_potential("tets", arrays, material, sc["dt"], sc["gravity"], free_only=True)
    solver = ImplicitEuler(pot, NewtonSettings(**sc["newton"]))
    rest = np.asarray(arrays["rest_positions"], dtype=np.float64)
    row = dict(modulus=modulus, law=law, frames=int(seq["frames"]), failed="-")
    t0 = time.perf_counter()
    try:
        data, _ = simulate_sequence(solver, rest, seq, sc["dt"], f"{scene} {law} {modulus:g}")
        positions = data["positions"]
    except SimulationError as e:
        # the message names scene, sequence and frame: "<label>, frame <t>: <why> (residual ...)"
        row["failed"] = "frame " + str(e).split(", frame ", 1)[1].split(":")[0]
        positions = None
    row["seconds"] = time.perf_counter() - t0
    if positions is not None:
        ratio, inverted = volume_ratios(positions, rest, arrays["tets"])
        row.update(solved=len(positions) - 1, inverted_frames=int((inverted > 0).sum()), min_det=float(ratio.min()))
    else:
        row.update(solved=None, inverted_frames=None, min_det=None)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--scene", default="armadillo")
    ap.add_argument("--moduli", type=float, nargs="+", default=[1e6, 3e5])
    ap.add_argument("--models", nargs="+", default=["stvk", "neohookean"])
    ap.add_argument("--frames", type=int, default=None, help="at most this many frames of the test sequence")
    args = ap.parse_args()
    cfg = load_config(args.config)
    sc = cfg["scenes"][args.scene]
    arrays, quality = scene_mesh(args.scene, sc["model"], sc["mesh"], sc["dirichlet"], cfg["meshes"])
    print(f"scene {args.scene}: {len(arrays['rest_positions'])} vertices, {len(arrays['tets'])} tets, "
          f"smallest dihedral angle {quality.get('dihedral_min_deg', float('nan')):.3g} deg")
    print("| Young's modulus [Pa] | material | frames | Newton failed at | frames ending inverted | smallest det F | seconds |")
    print("|---|---|---|---|---|---|---|")
    for modulus in args.moduli:
        for law in args.models:
            r = run(cfg, args.scene, arrays, modulus, law, args.frames)
            inv = "-" if r["inverted_frames"] is None else f"{r['inverted_frames']} of {r['solved']}"
            det = "-" if r["min_det"] is None else f"{r['min_det']:.3g}"
            print(f"| {modulus:.3g} | {law} | {r['frames']} | {r['failed']} | {inv} | {det} | {r['seconds']:.0f} |", flush=True)


if __name__ == "__main__":
    main()

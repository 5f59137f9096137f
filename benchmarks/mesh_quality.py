"""Tet quality of the scenes whose surface TetGen fills, with and without the surface remeshing.

For every scene of a config with ``mesh.target_vertices > 0`` (the default config's
armadillo, bunny_ears and nm_bunny), the mesh stage's mesh is built twice: "before" with
``mesh.quality.remesh: false`` (the surface as given, simplified by quadric edge collapse
where it alone has too many vertices) and "after" with the defaults (isotropic remeshing
first).  Printed per scene: the target and the after mesh's vertices and tets, the smallest
dihedral angle before -> after, the after mesh's tets under 5 degrees, the change of the
enclosed volume (the tets' total volume against the input surface's) and the seconds the
after mesh took.  Run from the repository root (the config's ``meshes.local_dir`` is
relative to it)::

    OMP_NUM_THREADS=1 python benchmarks/mesh_quality.py [--config config/config.yaml] [--scenes armadillo]
"""

from __future__ import annotations

import argparse
import copy
import logging
import time
from pathlib import Path

import numpy as np

from latentsim.config import load_config
from latentsim.mesh import build_mesh, read_mesh, surface_of
from latentsim.mesh.build import quality_gate
from latentsim.mesh.geometry import enclosed_volume, tet_volumes
from latentsim.mesh.quality import tet_min_dihedral
from latentsim.mesh.sources import mesh_file

ROOT = Path(__file__).resolve().parents[1]


def _input_volume(cfg: dict, sources: dict) -> float:
    """Volume enclosed by the scene file's surface, in the scene's units (after ``scale``)."""
    m = read_mesh(mesh_file(cfg["file"], sources, sha256=cfg.get("sha256")))
    surf = m.triangles if m.triangles is not None else surface_of(m.tets)
    return abs(enclosed_volume(m.vertices, surf)) * float(cfg.get("scale", 1.0)) ** 3


def measure(scene: str, cfg: dict, sources: dict) -> dict:
    """One scene's row: counts, angles before / after, volume change, seconds."""
    before_cfg = copy.deepcopy(cfg)
    before_cfg.setdefault("quality", {})["remesh"] = False
    before = build_mesh("tets", before_cfg, sources)
    t0 = time.perf_counter()
    after = build_mesh("tets", cfg, sources)
    seconds = time.perf_counter() - t0
    angle = tet_min_dihedral(after["rest_positions"], after["tets"])
    volume = tet_volumes(after["rest_positions"], after["tets"]).sum()
    return {"scene": scene, "target": int(cfg["target_vertices"]),
            "vertices": len(after["rest_positions"]), "tets": len(after["tets"]),
            "before": float(tet_min_dihedral(before["rest_positions"], before["tets"]).min()),
            "after": float(angle.min()), "under5": int((angle < 5.0).sum()),
            "gate": quality_gate(cfg),
            "volume_change": float(volume / _input_volume(cfg, sources) - 1.0),
            "seconds": seconds}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--scenes", nargs="*", help="default: every scene with target_vertices > 0")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    config = load_config(args.config)
    sources = config["meshes"]
    scenes = args.scenes or [s for s, sc in config["scenes"].items()
                             if sc.get("model") == "tets" and sc["mesh"].get("target_vertices")]
    print("| scene | target | vertices | tets | smallest dihedral before -> after [deg] "
          "| tets under 5 deg | gate [deg] | volume change | seconds |")
    print("|---|---|---|---|---|---|---|---|---|")
    for scene in scenes:
        r = measure(scene, config["scenes"][scene]["mesh"], sources)
        print(f"| {r['scene']} | {r['target']:,} | {r['vertices']:,} ({r['vertices'] / r['target'] - 1:+.1%}) "
              f"| {r['tets']:,} | {r['before']:.3g} -> {r['after']:.3g} | {r['under5']} | {r['gate']:g} "
              f"| {r['volume_change']:+.3%} | {r['seconds']:.1f} |", flush=True)


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()

"""Numbers printed in the papers, shown next to ours in the report tables.

Li et al. 2025, Table 1 (timings on an AMD Threadripper CPU) and Table 2
(network layers and the time of one single-vertex Jacobian-vector product).
Keys are this pipeline's scene names.
"""

from __future__ import annotations

# scene: (full-space DoF, latent DoF, simulation ms, integration ms, decoder ms, total ms)
LI2025_TABLE1 = {
    "hair_rotation": (10800, 4, 268.0, 0.264, 0.456, 0.720),
    "hair_translation": (5400, 4, 208.0, 0.172, 0.386, 0.558),
    "cloth": (576, 4, 18.83, 0.109, 0.163, 0.272),
    "armadillo": (10020, 12, 136.8, 0.253, 0.236, 0.489),
    "bunny_ears": (8046, 8, 112.6, 0.228, 0.198, 0.426),
}

# scene: (decoder layers, integrator layers, Jvp ms, ours total ms)
LI2025_TABLE2 = {
    "hair_rotation": ("512, 512, 512, 50", "512, 512, 512", 2.19, 0.720),
    "hair_translation": ("256, 256, 256, 50", "256, 256, 256", 1.51, 0.558),
    "cloth": ("200, 200, 200, 50", "32, 32", 0.564, 0.272),
    "armadillo": ("200, 200, 200, 50", "256, 256, 256, 256, 256", 0.649, 0.489),
    "bunny_ears": ("200, 200, 200, 50", "256, 256, 256, 256, 256", 0.632, 0.426),
}


def paper_scene(scene: str) -> str:
    """The paper scene a pipeline scene reproduces: ``<scene>_paper`` (the scene at the paper's
    network sizes, config/config.yaml) is ``<scene>``."""
    return scene.removesuffix("_paper")


def li2025_table1(scene: str):
    """Li et al. Table 1's row of a pipeline scene, or None."""
    return LI2025_TABLE1.get(paper_scene(scene))


def li2025_table2(scene: str):
    """Li et al. Table 2's row of a pipeline scene, or None."""
    return LI2025_TABLE2.get(paper_scene(scene))

"""What the workflow's rules and the stages both name, without the stages' dependencies.

The Snakefile reads these when it parses (the methods it plans jobs for, the sweep's wildcard values, the sizes
table's layers, the captions' energies); the stages that run those jobs read the same.  Nothing here imports
torch, numba or matplotlib, so a dry run, a malformed config's refusal and a cluster job's parse of the
Snakefile pay for none of them.
"""

from __future__ import annotations

from latentsim.physics.materials import energy_description, material_model

__all__ = ["BASELINES", "DYNAMICS_METHODS", "PAPER_ENERGIES", "SEEDED_BASELINES", "energy_note", "layers_text", "parse_label",
           "point_label", "scene_energies", "scene_energy_note"]

#: The classical baselines (``stages.baselines``), as a scene's ``baselines`` names them.
BASELINES = ("pca_reduced", "modes_reduced", "fulton_reduced", "neural_modes_reduced", "newton_1it")
# the baselines whose subspace is a network trained per seed (the autoencoder's decoder): rolled out once per
# seed; the others (linear subspaces, the full-space Newton, the Neural Modes of the scene's first seed) once
SEEDED_BASELINES = ("fulton_reduced",)


#: The Neural Modes subspace-dynamics study's methods (``neural_modes.dynamics.subspace_dynamics``).
DYNAMICS_METHODS = {  # slug: (label, linear modes only, per-step minimiser, with a cubature)
    "nm_lbfgs": ("Neural Modes, L-BFGS (the paper's solver)", False, "lbfgs", False),
    "nm_newton": ("Neural Modes, Gauss-Newton on J^T H J", False, "newton", False),
    "linear_newton": ("linear modes, Newton", True, "newton", False),
    "nm_lbfgs_cubature": ("Neural Modes, L-BFGS, cubature", False, "lbfgs", True),
    "nm_newton_cubature": ("Neural Modes, Gauss-Newton, cubature", False, "newton", True),
    "linear_newton_cubature": ("linear modes, Newton, cubature", True, "newton", True),
}


def point_label(latent_dim: int, size: int) -> str:
    """Wildcard value of a sweep point: ``r{latent_dim}_s{size index}``."""
    return f"r{int(latent_dim)}_s{int(size)}"


def parse_label(label: str) -> tuple[int, int]:
    """Inverse of :func:`point_label`."""
    r, s = label.split("_")
    if not (r.startswith("r") and s.startswith("s")):
        raise ValueError(f"sweep point label {label!r}: expected r<latent_dim>_s<size index>")
    return int(r[1:]), int(s[1:])


def layers_text(widths, pca_dim=None) -> str:
    """Layer widths as the paper's Table 2 prints them: decoder ``"200, 200, 200, 50"`` (hidden layers, then the PCA layer)."""
    w = [int(v) for v in widths] + ([int(pca_dim)] if pca_dim else [])
    return ", ".join(map(str, w))


#: The energy of the paper's columns: Wang et al.'s own, as their Table 1 names it for each model.
PAPER_ENERGIES = {"shell": "Discrete Shell", "tets": "Tetrahedron, StVK"}


def energy_note(model: str, material: dict) -> str:
    """Which energy each column of a Wang et al. table uses: ours (the scene's ``material.model``, its
    formulas and constants) and the paper's (the authors' own), for table notes and report captions."""
    law = material_model(model, material)
    paper = PAPER_ENERGIES.get(model, model)
    same = (
        "the same formulas as ours (material.model stvk_nm); absolute values still differ with the constants, sets and training lengths"
        if law == "stvk_nm"
        else f"not ours (material.model {law}): compare ratios between methods, not absolute values"
    )
    return (
        f"Energy of our columns: {energy_description(model, material)}. Energy of the paper's columns (named paper): "
        f"the authors' own ('{paper}', their Table 1), as they print them: {same}."
    )


def scene_energy_note(config: dict, scene: str) -> str:
    """:func:`energy_note` of a configured scene (report captions)."""
    sc = config["scenes"][scene]
    return energy_note(sc["model"], sc["material"])


def scene_energies(config: dict, scenes) -> str:
    """The elastic energy of each configured scene, in words (the summary's caption)."""
    return "; ".join(f"{s}: {energy_description(config['scenes'][s]['model'], config['scenes'][s]['material'])}" for s in scenes)

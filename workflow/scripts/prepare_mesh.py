"""Stage: mesh preparation (see latentsim.stages.mesh)."""
from latentsim.stages.mesh import prepare_mesh
from latentsim.utils import run_stage


def main(smk):
    p = smk.params.scene
    prepare_mesh(smk.wildcards.scene, p["model"], p["mesh"], p["dirichlet"], smk.params.sources, smk.output.mesh, smk.output.vtu)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

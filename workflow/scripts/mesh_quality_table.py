"""Stage: the mesh quality table of every scene (see latentsim.stages.mesh.write_quality_table)."""
from latentsim.stages.mesh import write_quality_table
from latentsim.utils import run_stage


def main(smk):
    write_quality_table(dict(zip(smk.params.scenes, smk.input.meshes)), smk.output.table)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

"""Stage: linear modes of a wang2024 scene (see latentsim.nm_pipeline.linear_modes_stage)."""
from latentsim.nm_pipeline import linear_modes_stage
from latentsim.utils import run_stage


def main(smk):
    linear_modes_stage(smk.input.mesh, smk.params.nm, smk.output.modes)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

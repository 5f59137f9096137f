"""Stage: linear modes of a wang2024 scene (see latentsim.stages.neural_modes.linear_modes_stage)."""
from latentsim.stages.neural_modes import linear_modes_stage
from latentsim.utils import run_stage


def main(smk):
    linear_modes_stage(smk.input.mesh, smk.params.nm, smk.output.modes)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

"""Stage: Neural Modes summary across scenes (see latentsim.stages.neural_modes.summary_stage)."""
from latentsim.stages.neural_modes import summary_stage
from latentsim.utils import run_stage


def main(smk):
    summary_stage(dict(zip(smk.params.scenes, smk.input.histories)), smk.output.csv, smk.output.markdown)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

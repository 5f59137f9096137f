"""Stage: Neural Modes training (see latentsim.stages.neural_modes.train_stage)."""
from latentsim.stages.neural_modes import train_stage
from latentsim.utils import run_stage


def main(smk):
    train_stage(smk.input.mesh, smk.input.modes, smk.params.nm, smk.params.seed, smk.output.model, smk.output.history)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

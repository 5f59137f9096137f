"""Stage: a reduced-order baseline's rollouts (see latentsim.baselines.baseline_rollouts)."""
from latentsim.baselines import baseline_rollouts
from latentsim.utils import run_stage


def main(smk):
    baseline_rollouts(smk.input.trajectories, smk.input.autoencoder, smk.params.method, smk.params.reduced["reduced"], smk.output.rollout)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

"""Stage: a reduced-order baseline's rollouts (see latentsim.stages.baselines.baseline_rollouts)."""
from latentsim.stages.baselines import baseline_rollouts
from latentsim.utils import run_stage


def main(smk):
    nm = list(smk.input.get("neural_modes", []))
    baseline_rollouts(smk.input.trajectories, smk.input.autoencoder, smk.params.method, smk.params.reduced["reduced"], smk.output.rollout,
                      neural_modes=nm[0] if nm else None, seed=int(smk.params.seed))  # fmt: skip


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

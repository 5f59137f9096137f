"""Stage: latent rollout of the test sequences (see latentsim.stages.rollout.rollout_scene)."""
from latentsim.stages.rollout import rollout_scene
from latentsim.utils import run_stage


def main(smk):
    rollout_scene(smk.input.trajectories, smk.input.autoencoder, smk.input.integrator, smk.params.rollout["rollout"], smk.output.rollout, method=smk.params.method, runtime_paths=(smk.output.runtime, smk.output.torch_export), seed=int(smk.params.seed))


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

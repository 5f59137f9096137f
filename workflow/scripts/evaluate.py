"""Stage: per-scene evaluation of the rollouts against the full simulation (see latentsim.stages.evaluate)."""
from latentsim.stages.evaluate import write_scene_evaluation
from latentsim.utils import run_stage


def main(smk):
    out = smk.output
    write_scene_evaluation(smk.wildcards.scene, smk.input.trajectories, list(smk.input.rollouts), smk.input.latents,
                           metrics=out.metrics, reconstruction=out.reconstruction, stress=out.stress, chart=out.chart,
                           figure=out.figure, full_time=smk.input.full_time)  # fmt: skip


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

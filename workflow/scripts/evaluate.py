"""Stage: per-scene evaluation of the rollout against the full simulation (see latentsim.evaluate)."""
from latentsim.evaluate import evaluate_scene, plot_curves, write_table
from latentsim.utils import run_stage


def main(smk):
    table, curves = evaluate_scene(smk.wildcards.scene, smk.input.trajectories, smk.input.rollout)
    write_table(table, smk.output.metrics)
    plot_curves(smk.wildcards.scene, curves, smk.output.figure)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

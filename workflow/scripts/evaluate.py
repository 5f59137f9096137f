"""Stage: per-scene evaluation of the rollout against the full simulation (see latentsim.report.evaluate)."""
from latentsim.report.evaluate import evaluate_scene, plot_curves, reconstruction_table, speed_accuracy_rows, stress_table, write_table
from latentsim.report.plots import speed_accuracy_chart
from latentsim.utils import run_stage


def main(smk):
    table, curves = evaluate_scene(smk.wildcards.scene, smk.input.trajectories, list(smk.input.rollouts))
    write_table(table, smk.output.metrics)
    write_table(reconstruction_table(smk.wildcards.scene, smk.input.latents), smk.output.reconstruction)
    write_table(stress_table(smk.wildcards.scene, list(smk.input.rollouts)), smk.output.stress)
    speed_accuracy_chart(speed_accuracy_rows(table), smk.output.chart, scene=smk.wildcards.scene)
    plot_curves(smk.wildcards.scene, curves, smk.output.figure)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

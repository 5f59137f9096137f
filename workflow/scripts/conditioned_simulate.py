"""Stage: a scene simulated at one condition (see latentsim.stages.conditioning.simulate_condition)."""
from latentsim.stages.conditioning import simulate_condition
from latentsim.utils import progress_enabled, run_stage


def main(smk):
    p = smk.params.sim
    simulate_condition(
        smk.wildcards.scene,
        smk.wildcards.condition,
        smk.input.mesh,
        p["sim"],
        p["condition"],
        smk.output.trajectories,
        paraview_dir=smk.output.paraview,
        progress=progress_enabled(smk.config.get("progress", True)),
    )


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

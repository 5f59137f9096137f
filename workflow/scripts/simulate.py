"""Stage: full-space simulation (see latentsim.stages.simulate)."""
from latentsim.stages.simulate import simulate_scene
from latentsim.utils import progress_enabled, run_stage


def main(smk):
    simulate_scene(
        smk.wildcards.scene,
        smk.input.mesh,
        smk.params.sim,
        smk.output.trajectories,
        paraview_dir=smk.output.paraview,
        progress=progress_enabled(smk.config.get("progress", True)),
    )


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

"""Stage: a scene simulated at one condition: the simulate stage (latentsim.stages.simulate.simulate_scene) on the
scene's config at that time step and modulus (latentsim.stages.conditioning.condition_sim_config), in the layout of
results/sim/<scene>/trajectories.h5."""
from latentsim.stages.conditioning import condition_sim_config
from latentsim.stages.simulate import simulate_scene
from latentsim.utils import progress_enabled, run_stage


def main(smk):
    p = smk.params.sim
    simulate_scene(
        f"{smk.wildcards.scene} at {smk.wildcards.condition}",
        smk.input.mesh,
        condition_sim_config(p["sim"], p["condition"]),
        smk.output.trajectories,
        paraview_dir=smk.output.paraview,
        progress=progress_enabled(smk.config.get("progress", True)),
    )


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

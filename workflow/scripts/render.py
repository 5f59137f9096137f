"""Stage: frames, clip and ParaView series of a scene's methods (see latentsim.stages.evaluate.render_scene)."""
from latentsim.stages.evaluate import render_scene
from latentsim.utils import run_stage


def main(smk):
    out = smk.output
    render_scene(smk.wildcards.scene, smk.input.trajectories, list(smk.input.rollouts), out.frames, out.clip, out.paraview)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

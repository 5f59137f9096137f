"""Stage: one sizing-sweep point (see latentsim.stages.sweep.sweep_point)."""
from latentsim.stages.sweep import sweep_point
from latentsim.utils import run_stage


def main(smk):
    p = smk.params.point
    trained = (smk.input.autoencoder, smk.input.integrator) if "integrator" in smk.input.keys() else None
    earlier = dict(smk.params.prune, metrics=list(smk.input.earlier)) if smk.params.prune else None
    sweep_point(smk.input.trajectories, p["autoencoder"], p["integrator"], p["rollout"], p["seed"], smk.output.metrics, device=p["device"],
                stress=p["stress"], trained=trained, earlier=earlier)  # fmt: skip


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

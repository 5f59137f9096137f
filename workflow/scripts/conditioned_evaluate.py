"""Stage: the conditioned integrator at the held-out conditions (see latentsim.stages.conditioning.evaluate_conditioned)."""
from latentsim.stages.conditioning import evaluate_conditioned
from latentsim.utils import run_stage


def main(smk):
    files = dict(smk.input.items())
    tests = {k.removeprefix("test_"): v for k, v in files.items() if k.startswith("test_")}
    models = {k.removeprefix("model_"): v for k, v in files.items() if k.startswith("model_")}
    evaluate_conditioned(
        tests,
        smk.input.autoencoder,
        models,
        smk.params.rollout["rollout"],
        int(smk.params.seed),
        smk.output.metrics,
        smk.output.frame_rate,
    )


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)

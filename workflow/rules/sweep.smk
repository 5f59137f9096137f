# Sizing sweep, one point and seed: train the autoencoder and integrator at one latent dimension and size, roll out, measure.
# A point that is exactly one of the scene's methods (same settings and seed) measures that method's trained model instead;
# a point's seeds run in order, and a seed is not trained once the earlier ones decide that the point cannot pass.
rule sweep_point:
    input:
        unpack(sweep_point_models),
        trajectories="results/sim/{scene}/trajectories.h5",
        earlier=sweep_earlier_metrics,
    output:
        metrics="results/sweep/{scene}/{point}/seed{seed}/metrics.csv",
    log:
        "logs/sweep/{scene}/{point}/seed{seed}.log",
    benchmark:
        "results/benchmarks/sweep/{scene}/{point}/seed{seed}.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=240,
        gpu=gpu_count,
    params:
        point=sweep_params,
        prune=sweep_prune_params,
    script:
        "../scripts/sweep_point.py"


# Sizing sweep, summary: the smallest model within the scene's tolerance in (a fraction of) its seeds, and the chart
# of error and speed against size with the seeds' spread.
rule sweep_summary:
    input:
        points=sweep_results,
    output:
        choice="results/sweep/{scene}/choice.csv",
        chart=report(
            "results/sweep/{scene}/sweep.png",
            caption="../report/sweep.rst",
            category="Sizing",
            subcategory="{scene}",
        ),
    log:
        "logs/sweep/{scene}/summary.log",
    conda:
        "../../envs/latentsim.yaml"
    params:
        tolerance=sweep_tolerance,
        pass_fraction=lambda w: config["scenes"][w.scene]["sweep"]["pass_fraction"],
        method=lambda w: config["scenes"][w.scene]["sweep"]["method"],
        sizes=lambda w: config["scenes"][w.scene]["sweep"]["sizes"],
        recorded=lambda w: config["scenes"][w.scene]["sweep"]["chosen"],
    script:
        "../scripts/sweep_summary.py"

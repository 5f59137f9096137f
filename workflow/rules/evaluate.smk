# Evaluation: errors of each rollout against the full simulation, speed-ups, and the summary tables.
rule evaluate:
    input:
        trajectories="results/sim/{scene}/trajectories.h5",
        rollout="results/rollout/{scene}/rollout.h5",
    output:
        metrics="results/evaluation/{scene}/metrics.csv",
        figure=report(
            "results/evaluation/{scene}/errors.png",
            caption="../report/errors.rst",
            category="Scenes",
            subcategory="{scene}",
        ),
    log:
        "logs/evaluation/{scene}.log",
    conda:
        "../../envs/latentsim.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/evaluate.py"


# Summary across scenes: one table (CSV + Markdown) and the speed-accuracy chart.
rule summary:
    input:
        metrics=expand("results/evaluation/{scene}/metrics.csv", scene=SCENES),
    output:
        csv=report(
            "results/evaluation/summary.csv",
            caption="../report/summary.rst",
            category="Summary",
        ),
        markdown="results/evaluation/summary.md",
        figure=report(
            "results/evaluation/speed_accuracy.png",
            caption="../report/speed_accuracy.rst",
            category="Summary",
        ),
    log:
        "logs/evaluation/summary.log",
    conda:
        "../../envs/latentsim.yaml"
    script:
        "../scripts/summary.py"

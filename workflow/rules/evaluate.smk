# Evaluation: errors of each rollout (every method and seed) against the full simulation, speed-ups, and the
# summary tables with the spread over seeds.


# The scene's full-space Newton frame timed once, in one process: the time every method's speed-up divides by.
rule time_full_space:
    input:
        trajectories="results/sim/{scene}/trajectories.h5",
    output:
        table="results/evaluation/{scene}/full_space_time.csv",
    log:
        "logs/evaluation/{scene}_full_space_time.log",
    benchmark:
        "results/benchmarks/time_full_space/{scene}.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    params:
        frames=lambda w: config["scenes"][w.scene]["rollout"]["full_frames_timed"],
    script:
        "../scripts/time_full_space.py"


# Evaluation of one scene: every method's rollouts against the ground truth, each step against the scene's one
# full-space time (rule time_full_space).
rule evaluate:
    input:
        trajectories="results/sim/{scene}/trajectories.h5",
        full_time="results/evaluation/{scene}/full_space_time.csv",
        rollouts=scene_rollouts,
        latents=lambda w: [
            f"{autoencoder_dir(config, w.scene, 'self_supervised', s)}/latents.h5"
            for s in scene_seeds(config, w.scene)
        ],
    output:
        metrics="results/evaluation/{scene}/metrics.csv",
        reconstruction="results/evaluation/{scene}/reconstruction.csv",
        stress="results/evaluation/{scene}/stress.csv",
        chart=report(
            "results/evaluation/{scene}/speed_accuracy.png",
            caption="../report/speed_accuracy_scene.rst",
            category="Scenes",
            subcategory="{scene}",
        ),
        figure=report(
            "results/evaluation/{scene}/errors.png",
            caption="../report/errors.rst",
            category="Scenes",
            subcategory="{scene}",
        ),
    log:
        "logs/evaluation/{scene}.log",
    benchmark:
        "results/benchmarks/evaluate/{scene}.tsv"
    conda:
        "../../envs/latentsim.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/evaluate.py"


# Pictures of the first test sequence: frames of every method (its first seed) beside the ground truth, a
# clip of the most telling failure and success, and XDMF series for ParaView.
rule render:
    input:
        trajectories="results/sim/{scene}/trajectories.h5",
        rollouts=lambda w: first_seed_rollouts(w.scene),
    output:
        frames=report(
            "results/evaluation/{scene}/frames.png",
            caption="../report/frames.rst",
            category="Scenes",
            subcategory="{scene}",
        ),
        clip=report(
            "results/evaluation/{scene}/clip.gif",
            caption="../report/clip.rst",
            category="Scenes",
            subcategory="{scene}",
        ),
        paraview=directory("results/evaluation/{scene}/paraview"),
    log:
        "logs/evaluation/{scene}_render.log",
    benchmark:
        "results/benchmarks/render/{scene}.tsv"
    conda:
        "../../envs/latentsim.yaml"
    resources:
        mem_mb=4000,
        runtime=20,
    script:
        "../scripts/render.py"


# Summary across scenes: one table (CSV + Markdown) and the speed-accuracy chart.
rule summary:
    input:
        metrics=expand("results/evaluation/{scene}/metrics.csv", scene=SCENES),
        reconstruction=expand(
            "results/evaluation/{scene}/reconstruction.csv", scene=SCENES
        ),
        stress=expand("results/evaluation/{scene}/stress.csv", scene=SCENES),
        sweeps=list(reported_sweep_choices().values()),
        owner=summary_owner,
    output:
        csv="results/evaluation/summary.csv",
        markdown="results/evaluation/summary.md",
        glance="results/evaluation/glance.csv",
        table1="results/evaluation/table1.csv",
        table2="results/evaluation/table2.csv",
        stability="results/evaluation/stability.csv",
        stress="results/evaluation/stress.csv",
        sizes="results/evaluation/sizes.csv",
        divergence="results/evaluation/divergence.csv",
        claims="results/evaluation/claims.md",
        owner=SUMMARY_OWNER,
        stress_map=report(
            "results/evaluation/stress_map.png",
            caption="../report/stress_map.rst",
            category="Summary",
            labels={"title": "Stress conditions: map"},
        ),
        figure=report(
            "results/evaluation/speed_accuracy.png",
            caption="../report/speed_accuracy.rst",
            category="Summary",
            labels={"title": "Speed against accuracy"},
        ),
    log:
        "logs/evaluation/summary.log",
    benchmark:
        "results/benchmarks/summary/summary.tsv"
    conda:
        "../../envs/latentsim.yaml"
    params:
        sizes=model_sizes(),
        sweep_choices=reported_sweep_choices(),
        scenes=SCENES,
    script:
        "../scripts/summary.py"

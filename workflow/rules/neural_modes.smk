# Neural Modes (Wang et al. 2024) for wang2024 scenes: linear modes, self-supervised training, summary,
# and the paper's evaluation studies that a scene's nm_study block switches on.
# NM_SCENES, neural_modes_targets (rule all's input) and the params input functions: common.smk
# (the params themselves: latentsim.rule_params).
from latentsim.labels import DYNAMICS_METHODS


# Lowest vibration modes of the rest state (sparse shift-invert), Dirichlet or rigid-free.
rule nm_linear_modes:
    input:
        mesh="results/mesh/{scene}/mesh.h5",
    output:
        modes="results/neural_modes/{scene}/linear_modes.h5",
    log:
        "logs/neural_modes/{scene}_linear_modes.log",
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    params:
        nm=nm_modes_params,
    script:
        "../scripts/nm_linear_modes.py"


# Self-supervised Neural Modes (Eq. 13): energy + orthogonality + origin, L-BFGS.
rule nm_train:
    input:
        mesh="results/mesh/{scene}/mesh.h5",
        modes="results/neural_modes/{scene}/linear_modes.h5",
    output:
        model="results/neural_modes/{scene}/neural_modes.pt",
        history="results/neural_modes/{scene}/history.h5",
    log:
        "logs/neural_modes/{scene}_train.log",
    benchmark:
        "results/benchmarks/neural_modes/{scene}.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=8000,
        runtime=240,
    params:
        nm=nm_train_params,
        seed=lambda w: scene_seeds(config, w.scene)[0],
    script:
        "../scripts/nm_train.py"


# One row per scene: energy against linear modes, constraint, origin, latent-direction correlation.
rule nm_summary:
    input:
        histories=expand("results/neural_modes/{scene}/history.h5", scene=NM_SCENES),
    output:
        csv="results/neural_modes/summary.csv",
        markdown="results/neural_modes/summary.md",
    log:
        "logs/neural_modes/summary.log",
    conda:
        "../../envs/latentsim.yaml"
    resources:
        mem_mb=1000,
        runtime=5,
    params:
        scenes=NM_SCENES,
    script:
        "../scripts/nm_summary.py"


# Ground truth of Eq. 9 on a study's sample sets (constrained Newton per sample); retraining never re-solves it.
# A killed job resumes from its checkpoint (the samples solved so far).
rule nm_ground_truth:
    input:
        mesh="results/mesh/{scene}/mesh.h5",
        modes="results/neural_modes/{scene}/linear_modes.h5",
    output:
        ground_truth="results/neural_modes/{scene}/{study}/ground_truth.h5",
    log:
        "logs/neural_modes/{scene}_{study}_ground_truth.log",
    benchmark:
        "results/benchmarks/neural_modes/{scene}_{study}_ground_truth.tsv"
    wildcard_constraints:
        study="sheet|energy",
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=8000,
        runtime=240,
    params:
        gt=nm_ground_truth_params,
        study="{study}",
        checkpoint="results/neural_modes/{scene}/{study}/ground_truth.checkpoint.npz",
    script:
        "../scripts/nm_ground_truth.py"


# Sheet study (Sec. 4.1-4.4): every method trained, and evaluated on validation and test along its training;
# once per seed of the scene (the ground truth's sample sets are the first seed's, shared).
rule nm_sheet_study:
    input:
        mesh="results/mesh/{scene}/mesh.h5",
        modes="results/neural_modes/{scene}/linear_modes.h5",
        ground_truth="results/neural_modes/{scene}/sheet/ground_truth.h5",
    output:
        study="results/neural_modes/{scene}/sheet/seed{seed}/study.h5",
    log:
        "logs/neural_modes/{scene}_sheet_study_seed{seed}.log",
    benchmark:
        "results/benchmarks/neural_modes/{scene}_sheet_study_seed{seed}.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=8000,
        runtime=240,
    params:
        nm=nm_study_params("sheet"),
    script:
        "../scripts/nm_sheet_study.py"


# Tables 2, 3, 4, A1 (ours beside the paper's, medians over the seeds with the spread) and Figs. 2, 3, 4
# of the sheet study.
rule nm_sheet_tables:
    input:
        study=lambda w: [
            f"results/neural_modes/{w.scene}/sheet/{seed_dir(s)}/study.h5"
            for s in scene_seeds(config, w.scene)
        ],
    output:
        markdown="results/neural_modes/{scene}/sheet/tables.md",
        table2="results/neural_modes/{scene}/sheet/table2.csv",
        table3="results/neural_modes/{scene}/sheet/table3.csv",
        table4="results/neural_modes/{scene}/sheet/table4.csv",
        tableA1="results/neural_modes/{scene}/sheet/tableA1.csv",
        correlation="results/neural_modes/{scene}/sheet/correlation.csv",
        structure="results/neural_modes/{scene}/sheet/structure.csv",
        learning_curves=report(
            "results/neural_modes/{scene}/sheet/learning_curves.png",
            caption="../report/nm_learning_curves.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
        latent_walk=report(
            "results/neural_modes/{scene}/sheet/latent_walk.png",
            caption="../report/nm_latent_walk.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
        correlation_figure=report(
            "results/neural_modes/{scene}/sheet/correlation.png",
            caption="../report/nm_correlation.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
    log:
        "logs/neural_modes/{scene}_sheet_tables.log",
    conda:
        "../../envs/latentsim.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/nm_sheet_tables.py"


# Table 5: PCA+AE (early-stopped on the validation L2) against the trained Neural Modes on uniform samples.
rule nm_energy_table:
    input:
        mesh="results/mesh/{scene}/mesh.h5",
        ground_truth="results/neural_modes/{scene}/energy/ground_truth.h5",
        model="results/neural_modes/{scene}/neural_modes.pt",
    output:
        csv="results/neural_modes/{scene}/energy/table5.csv",
        markdown="results/neural_modes/{scene}/energy/table5.md",
        history="results/neural_modes/{scene}/energy/history.h5",
    log:
        "logs/neural_modes/{scene}_energy_table.log",
    benchmark:
        "results/benchmarks/neural_modes/{scene}_energy_table.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=8000,
        runtime=120,
    params:
        nm=nm_study_params("energy"),
    script:
        "../scripts/nm_energy_table.py"


# Subspace dynamics (Eq. 15): Neural Modes and linear modes, with and without a cubature, against the full simulation.
rule nm_dynamics:
    input:
        trajectories="results/sim/{scene}/trajectories.h5",
        model="results/neural_modes/{scene}/neural_modes.pt",
    output:
        **{
            slug: f"results/neural_modes/{{scene}}/dynamics/{slug}.h5"
            for slug in DYNAMICS_METHODS
        },
        csv="results/neural_modes/{scene}/dynamics/dynamics.csv",
        markdown="results/neural_modes/{scene}/dynamics/dynamics.md",
        paraview=directory("results/neural_modes/{scene}/dynamics/paraview"),
    log:
        "logs/neural_modes/{scene}_dynamics.log",
    benchmark:
        "results/benchmarks/neural_modes/{scene}_dynamics.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=60,
    params:
        nm=nm_study_params("dynamics"),
    script:
        "../scripts/nm_dynamics.py"


# Keyframing (Fig. 6): modal coordinates interpolated linearly, decoded by Neural Modes and by linear modes.
rule nm_keyframes:
    input:
        mesh="results/mesh/{scene}/mesh.h5",
        model="results/neural_modes/{scene}/neural_modes.pt",
    output:
        figure=report(
            "results/neural_modes/{scene}/keyframes/keyframes.png",
            caption="../report/nm_keyframes.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
        motion="results/neural_modes/{scene}/keyframes/keyframes.h5",
        paraview=directory("results/neural_modes/{scene}/keyframes/paraview"),
    log:
        "logs/neural_modes/{scene}_keyframes.log",
    conda:
        "../../envs/latentsim.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        nm=nm_study_params("keyframes"),
    script:
        "../scripts/nm_keyframes.py"


# Aspect ratio as an auxiliary input (Sec. 4.3, Fig. A2): one network over a stretched sheet's ratios, every other held out.
rule nm_aspect_ratio:
    input:
        mesh="results/mesh/{scene}/mesh.h5",
    output:
        model="results/neural_modes/{scene}/aspect/neural_modes.pt",
        family="results/neural_modes/{scene}/aspect/family.h5",
        csv="results/neural_modes/{scene}/aspect/aspect.csv",
        markdown="results/neural_modes/{scene}/aspect/aspect.md",
        figure=report(
            "results/neural_modes/{scene}/aspect/aspect_ratio.png",
            caption="../report/nm_aspect.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
        paraview=directory("results/neural_modes/{scene}/aspect/paraview"),
    log:
        "logs/neural_modes/{scene}_aspect_ratio.log",
    benchmark:
        "results/benchmarks/neural_modes/{scene}_aspect_ratio.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=60,
    params:
        nm=nm_study_params("aspect"),
    script:
        "../scripts/nm_aspect_ratio.py"

# Full-space implicit-Euler simulation of every sequence of a scene (Newton on the incremental potential).
rule simulate:
    input:
        mesh="results/mesh/{scene}/mesh.h5",
        colliders=collider_files,
    output:
        trajectories="results/sim/{scene}/trajectories.h5",
        paraview=directory("results/sim/{scene}/paraview"),
    log:
        "logs/sim/{scene}.log",
    benchmark:
        "results/benchmarks/sim/{scene}.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=240,
    params:
        sim=sim_params,
    script:
        "../scripts/simulate.py"

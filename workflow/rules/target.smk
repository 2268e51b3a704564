rule target:
    input:
        mesh=f"{RESULTS}/{{mesh}}/normalize/mesh.ply",
        train=f"{RESULTS}/{{mesh}}/raycache/train.npz",
        metrics=f"{RESULTS}/{{mesh}}/raycache/metrics.npz",
    output:
        train=f"{RESULTS}/{{mesh}}/target/{{material}}/train.npz",
        metrics=f"{RESULTS}/{{mesh}}/target/{{material}}/metrics.npz",
        targets=f"{RESULTS}/{{mesh}}/target/{{material}}/targets.png",
        material=f"{RESULTS}/{{mesh}}/target/{{material}}/material.png",
        meta=f"{RESULTS}/{{mesh}}/target/{{material}}/meta.json",
    log:
        f"{RESULTS}/{{mesh}}/logs/target-{{material}}.log",
    benchmark:
        f"{RESULTS}/{{mesh}}/benchmarks/target-{{material}}.tsv"
    conda:
        CONDA_ENV
    threads: 2
    params:
        code=code_digest("stages.target"),
        out_dir=lambda wildcards: f"{RESULTS}/{wildcards.mesh}/target/{wildcards.material}",
        settings=stage_settings_json("target"),
    shell:
        "python -m stages.target --mesh {input.mesh:q} --train {input.train:q} --metrics {input.metrics:q} "
        "--material {wildcards.material} --out-dir {params.out_dir:q} --settings {params.settings:q} 2> {log:q}"

rule target:
    input:
        mesh=mesh_work_input("normalize", "mesh.ply"),
        train=mesh_work_input("raycache", "train.npz"),
        metrics=mesh_work_input("raycache", "metrics.npz"),
        envmaps=target_envmaps,
    output:
        train=f"{MESH_WORK_DIR}/target/{{material}}/train.npz",
        metrics=f"{MESH_WORK_DIR}/target/{{material}}/metrics.npz",
        relit=f"{MESH_WORK_DIR}/target/{{material}}/relit.npz",
        targets=f"{MESH_WORK_DIR}/target/{{material}}/targets.png",
        material=f"{MESH_WORK_DIR}/target/{{material}}/material.png",
        meta=f"{MESH_WORK_DIR}/target/{{material}}/meta.json",
    log:
        f"{MESH_WORK_DIR}/logs/target-{{material}}.log",
    benchmark:
        f"{MESH_WORK_DIR}/benchmarks/target-{{material}}.tsv"
    conda:
        CONDA_ENV
    threads: RULE_THREADS["target"]
    params:
        code=code_digest("stages.target"),
        out_dir=lambda wildcards: f"{MESHES}/{wildcards.mesh}/{wildcards.key}/target/{wildcards.material}",
        settings=stage_settings_json("target"),
    shell:
        "python -m stages.target --mesh {input.mesh:q} --train {input.train:q} --metrics {input.metrics:q} "
        "--material {wildcards.material} --out-dir {params.out_dir:q} --settings {params.settings:q} "
        "--threads {threads} 2> {log:q}"

rule raycache:
    input:
        mesh=traced_mesh,
    output:
        train=f"{MESH_WORK_DIR}/raycache/train.npz",
        eval=f"{MESH_WORK_DIR}/raycache/eval.npz",
        metrics=f"{MESH_WORK_DIR}/raycache/metrics.npz",
        meta=f"{MESH_WORK_DIR}/raycache/meta.json",
    log:
        f"{MESH_WORK_DIR}/logs/raycache.log",
    benchmark:
        f"{MESH_WORK_DIR}/benchmarks/raycache.tsv"
    conda:
        CONDA_ENV
    threads: RULE_THREADS["raycache"]
    params:
        code=code_digest("stages.raycache"),
        settings=stage_settings_json("raycache"),
    shell:
        "python -m stages.raycache --input {input.mesh:q} --train {output.train:q} "
        "--eval {output.eval:q} --metrics {output.metrics:q} --meta {output.meta:q} --settings {params.settings:q} "
        "--threads {threads} 2> {log:q}"

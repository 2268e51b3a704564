rule raycache:
    input:
        mesh=traced_mesh,
    output:
        train=f"{RESULTS}/{{mesh}}/raycache/train.npz",
        eval=f"{RESULTS}/{{mesh}}/raycache/eval.npz",
        metrics=f"{RESULTS}/{{mesh}}/raycache/metrics.npz",
        meta=f"{RESULTS}/{{mesh}}/raycache/meta.json",
    log:
        f"{RESULTS}/{{mesh}}/logs/raycache.log",
    benchmark:
        f"{RESULTS}/{{mesh}}/benchmarks/raycache.tsv"
    conda:
        CONDA_ENV
    params:
        code=code_digest("stages.raycache"),
        settings=stage_settings_json("raycache"),
    shell:
        "python -m stages.raycache --input {input.mesh:q} --train {output.train:q} "
        "--eval {output.eval:q} --metrics {output.metrics:q} --meta {output.meta:q} --settings {params.settings:q} 2> {log:q}"

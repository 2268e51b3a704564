rule metrics:
    input:
        unpack(cell_targets("metrics")),
        field=f"{CELL}/optimize/field.pt",
        cache=mesh_work_input("raycache", "metrics.npz"),
    output:
        metrics=f"{CELL}/metrics/metrics.json",
        views=f"{CELL}/metrics/views.png",
        meta=f"{CELL}/metrics/meta.json",
    log:
        f"{CELL}/logs/metrics.log",
    benchmark:
        f"{CELL}/benchmarks/metrics.tsv"
    conda:
        CONDA_ENV
    threads: 1
    resources:
        gpu=GPU_JOBS,
    params:
        code=code_digest("stages.metrics"),
        device=DEVICE,
        prompt=prompt_text,
        candidates=candidates_json,
        out_dir=cell_dir("metrics"),
        settings=cell_settings_json("metrics"),
        targets=targets_option,
    shell:
        "python -m stages.metrics --field {input.field:q} --metrics-cache {input.cache:q} "
        "--prompt={params.prompt:q} --candidates={params.candidates:q} --out-dir {params.out_dir:q} "
        "--settings {params.settings:q} {params.targets} --threads {threads} --device {params.device} 2> {log:q}"

rule roundtrip:
    input:
        unpack(roundtrip_inputs),
    output:
        compare=f"{CELL}/roundtrip/compare.png",
        meta=f"{CELL}/roundtrip/meta.json",
    log:
        f"{CELL}/logs/roundtrip.log",
    benchmark:
        f"{CELL}/benchmarks/roundtrip.tsv"
    conda:
        CONDA_ENV
    threads: 1
    resources:
        gpu=GPU_JOBS,
    params:
        code=code_digest("stages.roundtrip"),
        device=DEVICE,
        bake_dir=cell_dir("bake"),
        export_dir=cell_dir("export"),
        out_dir=cell_dir("roundtrip"),
        settings=cell_settings_json("roundtrip"),
        source=mesh_source,
    shell:
        "python -m stages.roundtrip --mesh {input.mesh:q} --transform {input.transform:q} "
        "--field {input.field:q} --eval {input.eval:q} --bake-dir {params.bake_dir:q} "
        "--export-dir {params.export_dir:q} --out-dir {params.out_dir:q} "
        "--settings {params.settings:q} --source={params.source:q} --threads {threads} --device {params.device} "
        "2> {log:q}"

rule bake:
    input:
        mesh=traced_mesh,
        field=f"{CELL}/optimize/field.pt",
        eval=mesh_work_input("raycache", "eval.npz"),
        transform=mesh_work_input("normalize", "transform.json"),
        source=mesh_input,
    output:
        **bake_outputs(),
    log:
        f"{CELL}/logs/bake.log",
    benchmark:
        f"{CELL}/benchmarks/bake.tsv"
    conda:
        CONDA_ENV
    threads: 1
    resources:
        gpu=GPU_JOBS,
    params:
        code=code_digest("stages.bake"),
        device=DEVICE,
        out_dir=cell_dir("bake"),
        settings=cell_settings_json("bake"),
        source=mesh_source,
    shell:
        "python -m stages.bake --mesh {input.mesh:q} --field {input.field:q} --eval {input.eval:q} "
        "--out-dir {params.out_dir:q} --settings {params.settings:q} --source={params.source:q} "
        "--transform {input.transform:q} --threads {threads} --device {params.device} 2> {log:q}"

rule relight:
    input:
        unpack(relight_inputs),
    output:
        relit=f"{CELL}/relight/relit.png",
        material_edit=f"{CELL}/relight/material_edit.png",
        light_fit=f"{CELL}/relight/light_fit.png",
        meta=f"{CELL}/relight/meta.json",
    log:
        f"{CELL}/logs/relight.log",
    benchmark:
        f"{CELL}/benchmarks/relight.tsv"
    conda:
        CONDA_ENV
    threads: 1
    resources:
        gpu=GPU_JOBS,
    params:
        code=code_digest("stages.relight"),
        device=DEVICE,
        out_dir=cell_dir("relight"),
        settings=cell_settings_json("relight"),
        truth=relight_truth_options,
    shell:
        "python -m stages.relight --field {input.field:q} --eval {input.eval:q} "
        "--out-dir {params.out_dir:q} --settings {params.settings:q} {params.truth} --threads {threads} --device {params.device} 2> {log:q}"

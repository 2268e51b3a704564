rule report:
    input:
        cell_metas("optimize/meta.json"),
        cell_metas("bake/meta.json"),
        cell_metas("asset/meta.json"),
        cell_metas("relight/meta.json"),
    output:
        summary=report(
            f"{RESULTS}/report/summary.csv",
            caption="../report/summary.rst",
            category="Summary",
        ),
        summary_json=f"{RESULTS}/report/summary.json",
        overview=report(
            f"{RESULTS}/report/overview.png",
            caption="../report/overview.rst",
            category="Summary",
        ),
    log:
        f"{RESULTS}/report/logs/report.log",
    benchmark:
        f"{RESULTS}/report/benchmarks/report.tsv"
    conda:
        CONDA_ENV
    params:
        cells=cell_ids(),
        results=results_root,
        out_dir=output_folder,
    shell:
        "python -m stages.report --results {params.results:q} --out-dir {params.out_dir:q} "
        "--cells {params.cells} 2> {log:q}"


rule pack:
    input:
        cell_metas("asset/meta.json"),
    output:
        zip=f"{RESULTS}/report/asset_pack.zip",
        index=f"{RESULTS}/report/asset_index.csv",
    log:
        f"{RESULTS}/report/logs/pack.log",
    benchmark:
        f"{RESULTS}/report/benchmarks/pack.tsv"
    conda:
        CONDA_ENV
    params:
        cells=cell_ids(),
        results=results_root,
    shell:
        "python -m stages.pack --results {params.results:q} --zip {output.zip:q} "
        "--index {output.index:q} --cells {params.cells} 2> {log:q}"

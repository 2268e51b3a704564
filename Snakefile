# TANGO stylization workflow. Run from the repository root:
#   snakemake --cores 2                              # the default experiment (config/config.yaml)
#   snakemake --cores 2 --configfile config/X.yaml   # another experiment (replaces the default)
# Rules describe files; the stages in stages/ do the work (rule <name> -> stages/<name>.py, writing
# <name>/); the layers beneath them are described in ARCHITECTURE.md.


include: "workflow/rules/common.smk"
include: "workflow/rules/normalize.smk"
include: "workflow/rules/decimate.smk"
include: "workflow/rules/raycache.smk"
include: "workflow/rules/target.smk"
include: "workflow/rules/optimize.smk"
include: "workflow/rules/bake.smk"
include: "workflow/rules/export.smk"
include: "workflow/rules/relight.smk"
include: "workflow/rules/metrics.smk"
include: "workflow/rules/roundtrip.smk"
include: "workflow/rules/lod.smk"
include: "workflow/rules/report.smk"


report: "workflow/report/workflow.rst"


onstart:
    check_needed_pieces()
    print_plan()


rule all:
    default_target: True
    input:
        all_targets(),

# Figures: each reads cached products only, so editing a plot never re-runs a fit.


rule plot_dark:
    input:
        dark=rules.measure_dark.output.dark,
        manifest=MANIFEST_FILE,
    output:
        dark_png=report(f"{OUT}/figures/dark.png", category="Dark", caption="../report/dark.rst"),
        dark_pdf=f"{OUT}/figures/dark.pdf",
        noise_png=report(f"{OUT}/figures/dark_noise.png", category="Dark", caption="../report/dark_noise.rst"),
        noise_pdf=f"{OUT}/figures/dark_noise.pdf",
    log:
        f"{OUT}/logs/plot_dark.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_dark"),
    params:
        code=code_version("plotting", "manifest", "io"),
    script:
        "../scripts/plot_dark.py"


rule plot_prnu:
    input:
        prnu=rules.measure_prnu.output.prnu,
        manifest=MANIFEST_FILE,
    output:
        png=report(f"{OUT}/figures/prnu_{{flat}}.png", category="PRNU", caption="../report/prnu.rst"),
        pdf=f"{OUT}/figures/prnu_{{flat}}.pdf",
    log:
        f"{OUT}/logs/plot_prnu_{{flat}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_prnu"),
    params:
        code=code_version("plotting", "manifest", "io"),
    script:
        "../scripts/plot_prnu.py"


rule plot_prnu_difference:
    input:
        difference=rules.compare_prnu.output.difference,
        manifest=MANIFEST_FILE,
    output:
        png=report(
            f"{OUT}/figures/prnu_difference_{{flat}}.png", category="PRNU", caption="../report/prnu_difference.rst"
        ),
        pdf=f"{OUT}/figures/prnu_difference_{{flat}}.pdf",
    log:
        f"{OUT}/logs/plot_prnu_difference_{{flat}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_prnu_difference"),
    params:
        code=code_version("plotting", "manifest", "io"),
    script:
        "../scripts/plot_prnu_difference.py"


rule plot_metrology:
    input:
        metrology=f"{OUT}/metrology/{{baseline}}.nc",
        manifest=MANIFEST_FILE,
    output:
        png=report(f"{OUT}/figures/metrology_{{baseline}}.png", category="Metrology", caption="../report/metrology.rst"),
        pdf=f"{OUT}/figures/metrology_{{baseline}}.pdf",
    log:
        f"{OUT}/logs/plot_metrology_{{baseline}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_metrology"),
    params:
        code=code_version("plotting", "manifest", "io"),
    script:
        "../scripts/plot_metrology.py"


rule plot_allan:
    input:
        allan=rules.allan_deviation.output.allan,
    output:
        png=report(f"{OUT}/figures/allan_{{baseline}}.png", category="Metrology", caption="../report/allan.rst"),
        pdf=f"{OUT}/figures/allan_{{baseline}}.pdf",
    log:
        f"{OUT}/logs/plot_allan_{{baseline}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_allan"),
    params:
        code=code_version("plotting", "io"),
    script:
        "../scripts/plot_allan.py"


rule plot_offsets:
    input:
        offsets=rules.deproject_offsets.output.offsets,
        manifest=MANIFEST_FILE,
    output:
        png=report(f"{OUT}/figures/offsets_{{pair}}.png", category="Metrology", caption="../report/offsets.rst"),
        pdf=f"{OUT}/figures/offsets_{{pair}}.pdf",
    log:
        f"{OUT}/logs/plot_offsets_{{pair}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_offsets"),
    params:
        code=code_version("plotting", "manifest", "io"),
    script:
        "../scripts/plot_offsets.py"


rule plot_prf:
    input:
        prf=rules.prf_widths.output.prf,
        manifest=MANIFEST_FILE,
    output:
        png=report(f"{OUT}/figures/prf.png", category="Metrology", caption="../report/prf.rst"),
        pdf=f"{OUT}/figures/prf.pdf",
    log:
        f"{OUT}/logs/plot_prf.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_prf"),
    params:
        code=code_version("plotting", "manifest", "io"),
    script:
        "../scripts/plot_prf.py"


rule plot_offsets_difference:
    input:
        difference=rules.compare_pairs.output.difference,
        manifest=MANIFEST_FILE,
    output:
        png=report(
            f"{OUT}/figures/offsets_difference_{{pair}}.png",
            category="Metrology",
            caption="../report/offsets_difference.rst",
        ),
        pdf=f"{OUT}/figures/offsets_difference_{{pair}}.pdf",
    log:
        f"{OUT}/logs/plot_offsets_difference_{{pair}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_offsets_difference"),
    params:
        code=code_version("plotting", "manifest", "io"),
    script:
        "../scripts/plot_offsets_difference.py"

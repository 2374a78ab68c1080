# Figures: each reads cached products only, so editing a plot never re-runs a fit.


rule plot_dark:
    input:
        dark=output_of("dark"),
        manifest=MANIFEST_FILE,
    output:
        **figure_of("figure_dark", "dark_", category="Dark", caption="dark"),
        **figure_of("figure_dark_noise", "noise_", category="Dark", caption="dark_noise"),
    log:
        f"{OUT}/logs/plot_dark.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_dark"),
    params:
        **step_params("plot_dark"),
    script:
        "../scripts/plot_dark.py"


rule plot_prnu:
    input:
        prnu=output_of("flat_prnu"),
        manifest=MANIFEST_FILE,
    output:
        **figure_of("figure_prnu", category="PRNU", caption="prnu"),
    log:
        f"{OUT}/logs/plot_prnu_{{flat}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_prnu"),
    params:
        **step_params("plot_prnu"),
    script:
        "../scripts/plot_prnu.py"


rule plot_prnu_difference:
    input:
        difference=output_of("prnu_difference"),
        manifest=MANIFEST_FILE,
    output:
        **figure_of("figure_prnu_difference", category="PRNU", caption="prnu_difference"),
    log:
        f"{OUT}/logs/plot_prnu_difference_{{flat}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_prnu_difference"),
    params:
        **step_params("plot_prnu_difference"),
    script:
        "../scripts/plot_prnu_difference.py"


rule plot_chromatic:
    input:
        chromatic=output_of("chromatic"),
        manifest=MANIFEST_FILE,
    output:
        **figure_of("figure_chromatic", category="Metrology", caption="chromatic"),
    log:
        f"{OUT}/logs/plot_chromatic.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_chromatic"),
    params:
        **step_params("plot_chromatic"),
    script:
        "../scripts/plot_chromatic.py"


rule plot_metrology:
    input:
        metrology=output_of("metrology"),
        manifest=MANIFEST_FILE,
    output:
        **figure_of("figure_metrology", category="Metrology", caption="metrology"),
    log:
        f"{OUT}/logs/plot_metrology_{{baseline}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_metrology"),
    params:
        **step_params("plot_metrology"),
    script:
        "../scripts/plot_metrology.py"


rule plot_allan:
    input:
        allan=output_of("allan"),
    output:
        **figure_of("figure_allan", category="Metrology", caption="allan"),
    log:
        f"{OUT}/logs/plot_allan_{{baseline}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_allan"),
    params:
        **step_params("plot_allan"),
    script:
        "../scripts/plot_allan.py"


rule plot_offsets:
    input:
        offsets=output_of("offsets"),
        manifest=MANIFEST_FILE,
    output:
        **figure_of("figure_offsets", category="Metrology", caption="offsets"),
    log:
        f"{OUT}/logs/plot_offsets_{{pair}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_offsets"),
    params:
        **step_params("plot_offsets"),
    script:
        "../scripts/plot_offsets.py"


rule plot_prf:
    input:
        prf=output_of("prf"),
        manifest=MANIFEST_FILE,
    output:
        **figure_of("figure_prf", category="Metrology", caption="prf"),
    log:
        f"{OUT}/logs/plot_prf.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_prf"),
    params:
        **step_params("plot_prf"),
    script:
        "../scripts/plot_prf.py"


rule plot_offsets_difference:
    input:
        difference=output_of("offsets_difference"),
        manifest=MANIFEST_FILE,
    output:
        **figure_of("figure_offsets_difference", category="Metrology", caption="offsets_difference"),
    log:
        f"{OUT}/logs/plot_offsets_difference_{{pair}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_offsets_difference"),
    params:
        **step_params("plot_offsets_difference"),
    script:
        "../scripts/plot_offsets_difference.py"


rule plot_stray_light:
    input:
        stray=output_of("stray_light"),
        manifest=MANIFEST_FILE,
    output:
        **figure_of("figure_stray_light", category="Metrology", caption="stray_light"),
    log:
        f"{OUT}/logs/plot_stray_light_{{baseline}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_stray_light"),
    params:
        **step_params("plot_stray_light"),
    script:
        "../scripts/plot_stray_light.py"

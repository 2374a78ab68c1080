"""The products catalogue: one entry per product, the docs page generated from it, io's check against it."""

import numpy as np
import pytest
import xarray as xr

from dice_core import centroids, products, products_page, steps
from dice_core.io import write_product, write_text

from conftest import REPO


def test_every_product_is_written_by_a_step_of_the_table_and_every_step_writes_one():
    for product in products.CATALOGUE.values():
        for name in (product.step, *product.extra):
            assert name in steps.STEPS, (product.key, name)
    for step in steps.STEPS.values():
        assert step.writes, step.name


def test_no_two_products_share_a_path_and_each_path_finds_its_entry():
    files = [(template, product) for product in products.CATALOGUE.values() for template in product.files()]
    assert len({(p.base, t) for t, p in files}) == len(files)
    values = {"flat": "fiber_b", "baseline": "H1H4", "pair": "P24", "position": "12", "mode": "flat+metrology",
              "method": "gaussian", "model": "pose", "npass": "3", "part": "1", "sweep": "tip_tilt",
              "point": "positions~6/tip_tilt_pv~0.0025", "relpath": "metrology/H1H4_000"}
    for template, product in files:
        path = ("results/sim-ci/" if product.base == "dataset" else "results/sweeps/") + template.format(**values)
        found, wildcards = products.match(path)
        assert found.key == product.key, (path, found.key)
        assert wildcards == {name: values[name] for name in product.wildcards}
    assert products.match("results/sim-ci/tables/procrustes_residuals.nc")[0].key == "procrustes_residuals"
    assert products.match("results/sim-ci/scratch/notes.nc") is None


def test_paths_are_built_under_their_base_folder():
    roots = {"dataset_root": "results/sim-ci", "sweeps_root": "results/sweeps"}
    assert products.pattern("metrology", **roots) == "results/sim-ci/metrology/{baseline}.nc"
    assert products.path_of("offsets", pair="P14", **roots) == "results/sim-ci/calibration/offsets_P14.nc"
    assert products.path_of("sweep_point", sweep="s", point="a~1", **roots) == "results/sweeps/s/a~1/point.nc"
    assert products.path_of("figure_prf", suffix=".pdf", **roots) == "results/sim-ci/figures/prf.pdf"
    with pytest.raises(ValueError, match="ask for its .png or .pdf"):
        products.pattern("figure_prf", **roots)
    with pytest.raises(KeyError, match="no value for baseline"):
        products.path_of("metrology", **roots)
    with pytest.raises(KeyError, match="no product 'nope'"):
        products.entry("nope")


def dark_product(**changes):
    values = {"dark": ("adu", ("row", "col")), "noise": ("adu", ("row", "col")),
              "saturated_count": ("1", ("row", "col"))}
    values.update(changes)
    return xr.Dataset({name: (dims, np.zeros((3, 3)), {"units": units}) for name, (units, dims) in values.items()
                       if units is not None})


def test_io_refuses_a_product_that_breaks_its_entry_and_writes_one_that_keeps_it(tmp_path):
    from dice_core.io import provenance

    results = tmp_path / "results" / "bench"
    with provenance(results=results):
        path = results / "calibration" / "dark.nc"
        write_product(dark_product(), path, title="dark")
        for changes, expected in [({"noise": (None, None)}, "variable noise is missing"),
                                  ({"dark": ("1", ("row", "col"))}, "variable dark is in '1', the catalogue says 'adu'"),
                                  ({"dark": ("adu", ("col", "row"))}, "variable dark has dims")]:
            with pytest.raises(ValueError, match=f"not what the catalogue's product dark promises: .*{expected}"):
                write_product(dark_product(**changes), path, title="dark")
        offsets = xr.Dataset({name: (("row", "col"), np.zeros((2, 3)), {"units": "pixel"})
                              for name in ("dx", "dy", "dx_photon_noise_floor", "dy_photon_noise_floor")})
        write_product(offsets, results / "calibration" / "offsets_P14.nc", title="offsets")  # no optional modes
        with pytest.raises(ValueError, match="table accuracy_table promises: no column n, rms_residual, factor, superimposition, unit"):
            write_text(results / "tables" / "accuracy.csv", "flat,metrology,grouping,accuracy,error,mode,method\n")
        # a file of the same name outside the results folder is no product of the workflow
        write_product(dark_product(noise=(None, None)), tmp_path / "mywork" / "calibration" / "dark.nc", title="x")
    write_product(dark_product(noise=(None, None)), path, title="outside any step: not checked")


def test_a_path_is_its_entry_relative_to_the_results_folder():
    root = "results/sim-ci"
    assert products.match("results/sim-ci/calibration/offsets_difference_P24.nc", root=root)[0].key == \
        "offsets_difference"
    assert products.match("results/sim-ci/stars/3.nc", root=root)[0].key == "stack"
    assert products.match("mywork/stars/catalogue.nc", root=root) is None
    assert products.match("results/sim-ci/raw/stars/3.nc", root=root) is None  # a raw file, not a stack


def test_the_products_page_is_generated_from_the_catalogue():
    """docs/products.md's generated part is the catalogue's: `python -m dice_core.products_page --write
    docs/products.md` after a change to dice_core/products.py."""
    page = (REPO / "docs" / "products.md").read_text()
    generated = products_page.markdown(modes=centroids.mode_descriptions(), methods=centroids.method_descriptions())
    assert generated in page, "docs/products.md is stale: run python -m dice_core.products_page --write docs/products.md"
    for product in products.CATALOGUE.values():
        assert f"`{product.files()[0]}`" in generated or f"results/sweeps/{product.files()[0]}" in generated
    for mode in centroids.MODES:
        assert f"- `{mode}`:" in generated
    with pytest.raises(ValueError, match="no generated part"):
        products_page.replace_generated("# a page\n", generated)
    assert products_page.replace_generated(page, generated) == page


def test_the_accuracy_table_entry_names_every_column_the_table_has():
    """The catalogue's columns of tables/accuracy.csv are the writer's own, in its order: a column added to
    the writer and not to the entry (as n, rms_residual and factor once were) fails here."""
    from dice_core import accuracies, products

    assert products.entry("accuracy_table").columns == accuracies.CSV_COLUMNS

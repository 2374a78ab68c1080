"""The README and docs/ stand alone: the README's two commands as CI runs them, an index naming every page."""

import re

from conftest import REPO


def test_the_readme_gives_the_two_commands_exactly_and_ci_runs_the_test_one():
    readme = (REPO / "README.md").read_text()
    run = "python3 -m pip install -e '.[workflow]' && python3 -m snakemake --cores 2"
    test = "python3 -m pip install -e '.[test]' && python3 -m pytest"
    assert run in readme and test in readme
    assert test in (REPO / ".ci" / "run").read_text()
    first_screen = "\n".join(readme.splitlines()[:45])  # what a newcomer sees first: the figure and both commands
    assert run in first_screen and test in first_screen and "docs/images/" in first_screen
    figure = re.search(r"!\[[^]]*\]\((docs/images/[^)]+\.png)\)", readme).group(1)
    assert (REPO / figure).is_file()


def test_the_docs_index_names_every_page_and_every_page_it_names_exists():
    index = (REPO / "docs" / "README.md").read_text()
    named = set(re.findall(r"`([\w./-]+\.md)`", index))
    pages = {p.name for p in (REPO / "docs").glob("*.md")} - {"README.md"}
    assert pages <= named, pages - named
    assert all((REPO / "docs" / name).is_file() for name in named), named
    readme = (REPO / "README.md").read_text()
    assert "docs/README.md" in readme


def test_every_figure_of_a_reduction_has_a_caption_in_docs_figures():
    """docs/figures.md names every figure the reduction's stages make (as figures/<name>, wildcards in angle
    brackets), so a figure added to the catalogue without a caption fails here."""
    from dice_core import products

    page = (REPO / "docs" / "figures.md").read_text()
    stages = {"dark and flat field", "metrology", "pseudo stars", "astrometry"}
    missing = [p.path for p in products.CATALOGUE.values()
               if p.kind == "figure" and p.stage in stages
               and f"`{p.path.removeprefix('figures/').replace('{', '<').replace('}', '>')}`" not in page]
    assert not missing, missing

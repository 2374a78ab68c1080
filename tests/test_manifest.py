"""Manifest validation: a valid dataset loads; every violation names the file and the problem."""

import copy
import pickle

import pytest
import yaml

from dice_core import DatasetError
from dice_core.manifest import ManifestError, load_manifest, parse_manifest
from dice_core.simulation import dataset_layout

from conftest import renamed, small_config


@pytest.fixture
def layout():
    return dataset_layout(small_config())


def write(tmp_path, document):
    path = tmp_path / "dataset.yaml"
    path.write_text(yaml.safe_dump(document))
    return path


def test_layout_parses_with_contract_structure(layout, tmp_path):
    manifest = parse_manifest(layout, tmp_path / "dataset.yaml")
    assert manifest.name == "sim-test"
    assert manifest.detector.shape == (40, 44)
    assert manifest.detector.science_slices == (slice(2, 39), slice(3, 43))
    assert manifest.reference_flat == "fiber_a"
    assert manifest.reference_pair == "P14"
    assert manifest.pairs["P24"] == ("H2H4", "V2V4")
    assert [p.index for p in manifest.positions] == [1, 2, 3]
    # file paths resolve against the manifest's folder
    assert manifest.dark.files[0] == (tmp_path / "dark/dark_000.fits").resolve()
    # the star order is fixed by approx: the central star first, given as [row, col]
    assert manifest.star_approx[0] == pytest.approx((20.2, 23.0), abs=0.5)


def test_only_required_sections(tmp_path, layout):
    document = {k: layout[k] for k in ("format", "name", "detector")}
    manifest = load_manifest(write(tmp_path, document))
    assert manifest.dark is None and not manifest.flats and not manifest.baselines and not manifest.positions


@pytest.mark.parametrize(
    "edit, expected",
    [
        (lambda d: d.update(format="dice-dataset/2"), "at format"),
        (lambda d: d.pop("detector"), "'detector' is a required property"),
        (lambda d: d.update(name="has space"), "manifest name .has space. is not a valid name"),
        (lambda d: d["detector"].update(gain=-1), "at detector.gain"),
        (lambda d: d["detector"].update(shape=[40]), "at detector.shape"),
        (lambda d: d["detector"]["science_area"].update(rows=[2, 41]), "science_area.rows"),
        (lambda d: d["detector"]["science_area"].update(cols=[10, 10]), "science_area.cols"),
        (lambda d: d["metrology"]["pairs"].update(P99=["H1H4", "X"]), "unknown baseline"),
        (lambda d: d["metrology"]["pairs"].update(P99=["H1H4", "H1H4"]), "twice"),
        (lambda d: d["dark"].update(files=[]), "at dark.files"),
        (lambda d: d.update(extra=1), "at extra: unknown key; keys allowed: format, name, detector"),
        (lambda d: d["stars"]["positions"].append(dict(d["stars"]["positions"][0])), "repeated indices"),
        (lambda d: d["stars"].update(approx=[[100, 3]]), "outside the detector"),
    ],
)
def test_violations_name_file_and_problem(layout, tmp_path, edit, expected):
    document = copy.deepcopy(layout)
    edit(document)
    path = write(tmp_path, document)
    with pytest.raises(DatasetError, match=expected) as info:
        load_manifest(path, check_files=False)
    assert str(path.resolve()) in str(info.value)


def test_missing_manifest(tmp_path):
    with pytest.raises(DatasetError, match="manifest not found") as info:
        load_manifest(tmp_path / "nowhere.yaml")
    assert "nowhere.yaml" in str(info.value)


def test_unreadable_manifest(tmp_path):
    path = tmp_path / "dataset.yaml"
    path.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(DatasetError, match="unreadable"):
        load_manifest(path)


def test_not_yaml(tmp_path):
    path = tmp_path / "dataset.yaml"
    path.write_text("format: [unclosed\n")
    with pytest.raises(DatasetError, match="not valid YAML"):
        load_manifest(path)


def test_missing_fits_file_is_named(layout, tmp_path):
    path = write(tmp_path, layout)
    with pytest.raises(DatasetError, match="not found") as info:
        load_manifest(path)
    assert "dark_000.fits" in str(info.value)


GEOMETRY = {"wavelength": 633.0e-9, "pixel_pitch": 24.0e-6,
            "fibers": {"F1": [0.0153, 0.0201, 0.6], "F4": [0.0087, 0.0201, 0.6], "F2": [0.0120, 0.0260, 0.6]},
            "baseline_fibers": {"H1H4": ["F1", "F4"], "V1V4": ["F2", "F4"], "H2H4": ["F2", "F1"],
                                "V2V4": ["F4", "F2"]}}


def test_the_bench_geometry_of_format_1_1_is_read(layout, tmp_path):
    document = copy.deepcopy(layout)
    document["metrology"]["geometry"] = copy.deepcopy(GEOMETRY)
    geometry = parse_manifest(document, tmp_path / "dataset.yaml").geometry
    assert geometry.wavelength == 633.0e-9 and geometry.pixel_pitch == 24.0e-6
    assert geometry.fibers["F1"] == (0.0153, 0.0201, 0.6) and geometry.baseline_fibers["H1H4"] == ("F1", "F4")
    assert parse_manifest(layout, tmp_path / "dataset.yaml").geometry is None


@pytest.mark.parametrize("edit, expected", [
    (lambda g: g["baseline_fibers"].update(H1H4=["F1", "F9"]), r"baseline_fibers.H1H4 names unknown fiber\(s\) \['F9'\]"),
    (lambda g: g["baseline_fibers"].update(X1X2=["F1", "F4"]), "names unknown baseline X1X2"),
    (lambda g: g["baseline_fibers"].pop("V2V4"), r"gives no fibers for baseline\(s\) \['V2V4'\]"),
    (lambda g: g["baseline_fibers"].update(H1H4=["F1", "F1"]), "H1H4: its two fibers are at one position"),
    (lambda g: g["fibers"].update(F1=[0.0, 0.0]), "at metrology.geometry.fibers.F1"),
    (lambda g: g.pop("wavelength"), "'wavelength' is a required property"),
    (lambda g: g.update(pixel_pitch=24.0), "pixel_pitch 24.0 is not in metres"),
    (lambda g: g["fibers"].update(F1=[0.0153, 0.0201, -0.6]), "F1 .* is not a finite position with z > 0"),
    (lambda g: g["fibers"].update(F1=[0.0087, 0.0201, 0.6]), "H1H4: its two fibers are at one position"),
])
def test_a_bad_bench_geometry_names_the_problem(layout, tmp_path, edit, expected):
    document = copy.deepcopy(layout)
    document["metrology"]["geometry"] = copy.deepcopy(GEOMETRY)
    edit(document["metrology"]["geometry"])
    with pytest.raises(DatasetError, match=expected):
        parse_manifest(document, tmp_path / "dataset.yaml")


# Names that would leave the results folder, or write somewhere it should not, if they became part of a path.
HOSTILE_NAMES = ["..", ".", "../x", "/tmp/x", "a/b", "{x}", ".hidden", "", "x" * 65, "a b", "a\n", "a\nb"]


@pytest.mark.parametrize("key, where", [("name", "manifest name"), ("flat", "manifest flats key"),
                                        ("baseline", "manifest metrology.baselines key"),
                                        ("pair", "manifest metrology.pairs key")])
@pytest.mark.parametrize("name", HOSTILE_NAMES)
def test_a_name_that_could_leave_its_folder_is_refused_naming_the_key_and_the_value(layout, tmp_path, key, where,
                                                                                      name):
    with pytest.raises(DatasetError) as info:
        parse_manifest(renamed(layout, key, name), tmp_path / "dataset.yaml")
    assert str(info.value).startswith(f"{tmp_path / 'dataset.yaml'}: {where} {name!r} is not a valid name")
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("name", ["sim-2024.v2", "H1H4_633", "-x", "A" * 64])
def test_names_that_stay_in_their_folder_are_accepted(layout, tmp_path, name):
    for key in ("name", "flat", "baseline", "pair"):
        parse_manifest(renamed(layout, key, name), tmp_path / "dataset.yaml")


def test_a_name_problem_comes_before_the_manifest_s_other_problems(layout, tmp_path):
    document = renamed(layout, "baseline", "../../victim")
    document["detector"]["gain"] = -1  # sorts before metrology.baselines
    with pytest.raises(DatasetError, match=r"metrology.baselines key '../../victim' is not a valid name:"
                                           r".* \(and 1 more problem: python3 -m dice_core check .*dataset.yaml "
                                           r"lists them all\)$"):
        parse_manifest(document, tmp_path / "dataset.yaml")


def misspelt(layout, *keys):
    """The layout with each ``(section, key)`` of ``keys`` misspelt by a dropped letter."""
    document = copy.deepcopy(layout)
    for section, key in keys:
        document[section][key[:-2] + key[-1]] = document[section].pop(key)
    return document


@pytest.mark.parametrize("keys, more", [
    ([("detector", "saturation")], ""),
    ([("detector", "saturation"), ("dark", "files")], " (and 1 more problem: "),
    ([("detector", "saturation"), ("dark", "files"), ("detector", "gain")], " (and 2 more problems: "),
])
def test_each_schema_problem_is_one_line_naming_the_key_path_and_the_message_counts_the_rest(layout, tmp_path,
                                                                                             keys, more):
    path = tmp_path / "dataset.yaml"
    with pytest.raises(ManifestError) as info:
        parse_manifest(misspelt(layout, *keys), path)
    error = info.value
    expected = sorted(f"manifest violates dice-dataset/1 at {section}.{key[:-2] + key[-1]}: unknown key; did you "
                      f"mean {key}? (a required key)" for section, key in keys)
    assert sorted(error.problems) == expected  # the key made missing by each typo is not a second problem
    assert str(error).startswith(f"{path.resolve()}: {error.problems[0]}{more}") and "\n" not in str(error)
    assert str(error).endswith(f"python3 -m dice_core check {path.resolve()} lists them all)" if more else "(a required key)")
    assert pickle.loads(pickle.dumps(error)).problems == error.problems  # crosses from a worker process intact


def test_a_typo_beside_the_key_it_resembles_is_not_called_a_missing_required_key(layout, tmp_path):
    document = copy.deepcopy(layout)
    document["detector"]["gian"] = 1.0  # gain is there: the typo is an extra key, not why gain is missing
    with pytest.raises(ManifestError) as info:
        parse_manifest(document, tmp_path / "dataset.yaml")
    assert info.value.problems == ("manifest violates dice-dataset/1 at detector.gian: unknown key; did you mean "
                                   "gain?",)


@pytest.mark.parametrize("text, expected", [
    ("", "manifest is empty"),
    ("# only a comment\n", "manifest is empty"),
    ("- format\n- name\n", "manifest is a list, not a mapping of keys"),
    ("dice-dataset/1\n", "manifest is a str, not a mapping of keys"),
])
def test_a_manifest_that_is_not_a_mapping_says_what_it_is(tmp_path, text, expected):
    path = tmp_path / "dataset.yaml"
    path.write_text(text)
    with pytest.raises(DatasetError, match=expected):
        load_manifest(path)


def test_a_key_given_twice_is_refused_at_any_level_naming_it_and_its_lines(layout, tmp_path):
    """A second H1H4 holding H2H4's files used to replace the first silently, and the run reduced the wrong
    cubes with exit status 0."""
    text = yaml.safe_dump(layout, sort_keys=False)
    second = text.replace("    H2H4:\n", "    H1H4:\n", 1)
    assert second != text
    path = tmp_path / "dataset.yaml"
    path.write_text(second)
    with pytest.raises(DatasetError) as info:
        load_manifest(path, check_files=False)
    first_line = text.splitlines().index("    H1H4:") + 1
    second_line = text.splitlines().index("    H2H4:") + 1
    assert str(info.value) == (f"{path}: manifest key metrology.baselines.H1H4 is given twice (lines {first_line} "
                               f"and {second_line}); YAML would keep the second silently")
    path.write_text(text + "name: other\n")
    with pytest.raises(DatasetError, match="manifest key name is given twice"):
        load_manifest(path, check_files=False)


# ------------------------------------------------------------------ format 1.2: several wavelengths

SPECTRUM = {"wavelength": [400.0e-9, 500.0e-9, 600.0e-9, 700.0e-9], "weight": [0.6, 1.0, 0.95, 0.7]}


def several_wavelengths(layout):
    """The layout with P14 at 633 nm (its baselines' own wavelength), P24 at 450 nm, a laser flat at 450 nm
    and the stars' spectrum: the example of docs/dataset-format.md."""
    document = copy.deepcopy(layout)
    baselines = document["metrology"]["baselines"]
    for name, wavelength in (("H1H4", 633e-9), ("V1V4", 633e-9), ("H2H4", 450e-9), ("V2V4", 450e-9)):
        baselines[name]["wavelength"] = wavelength
    document["flats"]["fiber_b"]["wavelength"] = 450e-9
    document["stars"]["spectrum"] = copy.deepcopy(SPECTRUM)
    return document


def test_format_1_2_wavelengths_and_spectrum_are_read(layout, tmp_path):
    manifest = parse_manifest(several_wavelengths(layout), tmp_path / "dataset.yaml")
    assert manifest.baselines["H2H4"].wavelength == 450e-9 and manifest.baseline_wavelength("H1H4") == 633e-9
    assert manifest.pair_wavelength("P24") == 450e-9
    assert manifest.wavelengths == (633e-9, 450e-9)  # in the order of their first pair
    assert manifest.pairs_at(450e-9) == ["P24"] and manifest.flats_at(450e-9) == ["fiber_b"]
    assert manifest.flats["fiber_a"].wavelength is None  # broadband
    assert manifest.spectrum.wavelength == tuple(SPECTRUM["wavelength"])
    assert manifest.spectrum.weight == tuple(SPECTRUM["weight"])
    # formats 1 and 1.1 state none
    plain = parse_manifest(layout, tmp_path / "dataset.yaml")
    assert plain.wavelengths == () and plain.spectrum is None and plain.baseline_wavelength("H1H4") is None


def test_wavelengths_equal_to_the_picometre_are_one_laser_s(layout, tmp_path):
    """Another program may write 633e-9 as 6.330000000001e-07: the same laser, not a pair mixing wavelengths."""
    document = several_wavelengths(layout)
    document["metrology"]["baselines"]["V1V4"]["wavelength"] = 633.0000000001e-9
    document["flats"]["fiber_b"]["wavelength"] = 449.9999999999e-9
    manifest = parse_manifest(document, tmp_path / "dataset.yaml")
    assert manifest.wavelengths == (633e-9, 450e-9) and manifest.flats_at(450e-9) == ["fiber_b"]
    document["metrology"]["baselines"]["V1V4"]["wavelength"] = 633.002e-9  # 2 pm: another laser, said so
    with pytest.raises(DatasetError, match="H1H4 at 633 nm, V1V4 at 633.002 nm"):
        parse_manifest(document, tmp_path / "dataset.yaml")


def test_a_baseline_without_a_wavelength_takes_the_geometry_s(layout, tmp_path):
    document = several_wavelengths(layout)
    document["metrology"]["geometry"] = copy.deepcopy(GEOMETRY)
    del document["metrology"]["baselines"]["V1V4"]["wavelength"]  # the geometry's 633 nm: P14 still one wavelength
    manifest = parse_manifest(document, tmp_path / "dataset.yaml")
    assert manifest.baseline_wavelength("V1V4") == 633e-9 and manifest.wavelengths == (633e-9, 450e-9)


@pytest.mark.parametrize("edit, expected", [
    # a pair mixing wavelengths, the first case; a stated and an unstated one mix too
    (lambda d: d["metrology"]["baselines"]["V1V4"].update(wavelength=450e-9),
     r"metrology.pairs.P14 mixes wavelengths: H1H4 at 633 nm, V1V4 at 450 nm; both baselines of a pair must "
     r"share one$"),
    (lambda d: d["metrology"]["baselines"]["V1V4"].pop("wavelength"),
     "metrology.pairs.P14 mixes wavelengths: H1H4 at 633 nm, V1V4 at no stated wavelength"),
    # a spectrum without wavelengths, the second
    (lambda d: d["stars"]["spectrum"].pop("wavelength"),
     r"at stars.spectrum: 'wavelength' is a required property$"),
    (lambda d: d["stars"]["spectrum"].update(weight=[1.0, 1.0]), "stars.spectrum gives 4 wavelength.s. and 2 "
                                                                 "weight.s.; one weight per wavelength"),
    (lambda d: d["stars"]["spectrum"].update(wavelength=[400, 500, 600, 700]),
     r"stars.spectrum.wavelength 400 is not in metres"),
    (lambda d: d["stars"]["spectrum"].update(wavelength=[400e-9, 600e-9, 500e-9, 700e-9]),
     "stars.spectrum.wavelength is not strictly increasing"),
    (lambda d: d["stars"]["spectrum"].update(weight=[0, 0, 0, 0]), "stars.spectrum.weight is zero everywhere"),
    (lambda d: d["stars"]["spectrum"].update(weight=[1, -1, 1, 1]), r"at stars.spectrum.weight.1: -1 is less"),
    (lambda d: d["metrology"]["baselines"]["H2H4"].update(wavelength=450.0),
     r"metrology.baselines.H2H4.wavelength 450.0 is not in metres"),
    (lambda d: d["flats"]["fiber_b"].update(wavelength=0.45), r"flats.fiber_b.wavelength 0.45 is not in metres"),
    (lambda d: d["dark"].update(wavelength=450e-9), "at dark.wavelength: unknown key"),  # a dark has none
    (lambda d: d["stars"]["spectrum"].update(weight=[1, float("inf"), 1, 1]),
     r"stars.spectrum.weight holds a value that is not finite and non-negative"),
    # a spectrum with no stated wavelength of the lasers to go with: the second case, read the other way
    (lambda d: [b.pop("wavelength") for b in d["metrology"]["baselines"].values()],
     r"stars.spectrum is given but no baseline states a wavelength"),
])
def test_a_bad_format_1_2_manifest_gets_one_line_naming_the_key(layout, tmp_path, edit, expected):
    document = several_wavelengths(layout)
    edit(document)
    with pytest.raises(DatasetError, match=expected) as info:
        parse_manifest(document, tmp_path / "dataset.yaml")
    assert "\n" not in str(info.value)

"""Command-line overrides of a pipeline (`--set path.to.field=value`): parsed as YAML, a stage chosen by its name,
refused with the override named, and a run name of their own."""

from __future__ import annotations

from pathlib import Path

import pytest

from spiral.config import SpecError
from spiral.config.load import load_pipeline
from spiral.config.overrides import apply_overrides, parse_override, variant_name

ROOT = Path(__file__).resolve().parents[2]
FULL = ROOT / "pipelines" / "full.yaml"


def test_an_override_value_is_parsed_as_yaml():
    assert parse_override("stages.1v1.iterations=600") == (("stages", "1v1", "iterations"), 600)
    assert parse_override("report.racing=null") == (("report", "racing"), None)
    assert parse_override("mix={solo: 1}") == (("mix",), {"solo": 1})
    assert parse_override("name=a=b") == (("name",), "a=b")
    for bad in ("seed", "=1", "a..b=1", "a={b"):
        with pytest.raises(SpecError, match="--set"):
            parse_override(bad)


def test_a_nested_field_set_on_the_command_line_reaches_only_the_stage_it_names():
    """`stages.1v1.iterations` sets the 1v1 stage's budget (found by name, not position), a missing table on the way
    is created, and the other stages and the file's own data stay as they were."""
    spec, _ = load_pipeline(FULL, ["stages.1v1.iterations=600", "stages.2v2.env.action.separation.distance=0.4"])
    plain, _ = load_pipeline(FULL)
    stages, before = {s.name: s for s in spec.stages}, {s.name: s for s in plain.stages}
    assert stages["1v1"].iterations == 600 and before["1v1"].iterations == 1200
    assert stages["1v1-noselfplay"].iterations == before["1v1-noselfplay"].iterations
    assert stages["2v2"].env.action.separation.distance == pytest.approx(0.4)
    assert stages["2v2"].env.action.separation.horizon_s == pytest.approx(0.4)  # the block's default
    assert before["2v2"].env.action.separation is None
    assert stages["2v2-noselfplay"].env.action.separation is None  # it names the same YAML anchor as 2v2
    data = {"stages": [{"name": "solo", "iterations": 3}]}
    assert apply_overrides(data, ["stages.solo.iterations=4"], source="p.yaml")["stages"][0]["iterations"] == 4
    assert data["stages"][0]["iterations"] == 3


def test_an_override_of_a_stage_does_not_reach_the_stages_that_share_its_yaml_anchor():
    """`full.yaml`'s 2v2 stages of both branches name one `env` anchor, and its multi-drone stages merge one `<<:`
    table: setting a field of one stage leaves the others' values, those they share too, as the file gives them."""
    spec, _ = load_pipeline(FULL, ["stages.2v2.env.episode.start_cut_prob=0.8", "stages.1v1.ppo.entropy_coef=0.01"])
    plain, _ = load_pipeline(FULL)
    stages, before = {s.name: s for s in spec.stages}, {s.name: s for s in plain.stages}
    assert stages["2v2"].env.episode.start_cut_prob == pytest.approx(0.8)
    assert stages["1v1"].ppo.entropy_coef == pytest.approx(0.01)
    for name in ("solo", "1v1-noselfplay", "2v2-noselfplay"):
        assert stages[name] == before[name], name
    assert stages["2v2"].env.obs == before["2v2"].env.obs


def test_a_wrong_override_is_refused_naming_the_file_and_the_override():
    with pytest.raises(SpecError, match=r"full\.yaml: --set stages\.nope\.iterations=5: stages\.nope: no entry "
                                        r"named 'nope' \(entries: solo, 1v1"):
        load_pipeline(FULL, ["stages.nope.iterations=5"])
    with pytest.raises(SpecError, match=r"--set stages\.1v1\.iteratoins=5.*iteratoins"):
        load_pipeline(FULL, ["stages.1v1.iteratoins=5"])
    with pytest.raises(SpecError, match=r"--set stages\.1v1\.iterations=-3.*iterations"):
        load_pipeline(FULL, ["stages.1v1.iterations=-3"])
    with pytest.raises(SpecError, match=r"--set seed\.x=1: seed: is int, not a table"):
        load_pipeline(FULL, ["seed.x=1"])
    with pytest.raises(SpecError, match=r"p\.yaml: --set stages\.solo=1: stages: set a field of one entry"):
        apply_overrides({"stages": [{"name": "solo"}]}, ["stages.solo=1"], source="p.yaml")


def test_overrides_name_the_run_so_that_two_seeds_never_share_a_folder():
    assert variant_name("full", []) == "full"
    assert variant_name("full", ["seed=1"]) == "full-seed-1"
    assert variant_name("full", ["seed=1", "stages.1v1.iterations=600"]) == "full-seed-1_stages.1v1.iterations-600"
    long = variant_name("full", ["stages.2v2.env.episode.passage_starts={share_start: 0.5, share_end: 0.2}"])
    assert long.startswith("full-") and len(long) == len("full-") + 12
    assert load_pipeline(FULL, ["seed=1"])[0].name == "full-seed-1"
    assert load_pipeline(FULL)[0].name == "full"

"""Loading: every rule of the track format fails naming the file and the field; pipelines load their track."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from pydantic import ValidationError

from spiral.config import SpecError, load_pipeline, load_spec, load_track

ROOT = Path(__file__).resolve().parents[2]
FIXTURES = Path(__file__).parent / "fixtures"

# Rules not covered by the fixtures in test_specs.py: start box, bounds, per-gate bar, direction, top level.
MALFORMED = {
    "start_in_gate.yaml": ("start", "start box intersects gates.0"),
    "start_outside_bounds.yaml": ("start", "start box leaves the arena bounds"),
    "bounds_inverted.yaml": ("bounds", "bounds.min must be below bounds.max"),
    "gate_bar_zero.yaml": ("gates.1.bar", "greater than 0"),
    "bad_direction.yaml": ("gates.0.direction", "1 or -1"),
}


@pytest.mark.parametrize(("name", "expected"), sorted(MALFORMED.items()))
def test_geometry_rule_names_the_file_and_the_field(name, expected):
    """Fail with one line `<file>: <field>: <message>` for each broken track rule."""
    field, message = expected
    with pytest.raises(SpecError) as info:
        load_track(FIXTURES / name)
    assert len(info.value.problems) == 1
    assert info.value.problems[0].startswith(f"{FIXTURES / name}: {field}: ")
    assert message in info.value.problems[0]


def test_every_problem_gets_its_own_line(tmp_path):
    """Report an unknown key and a negative time limit in one file as two lines."""
    text = (ROOT / "tracks" / "oval4.yaml").read_text().replace("time_limit_s: 20.0", "time_limit_s: -1\nlapz: 2")
    path = tmp_path / "two.yaml"
    path.write_text(text)
    with pytest.raises(SpecError) as info:
        load_spec(path)
    assert sorted(line.split(": ")[1] for line in info.value.problems) == ["lapz", "time_limit_s"]
    assert all(line.startswith(f"{path}: ") for line in info.value.problems)


def test_missing_file_names_the_file(tmp_path):
    """Say the file cannot be read, naming it."""
    with pytest.raises(SpecError) as info:
        load_spec(tmp_path / "nope.yaml")
    assert info.value.problems == [f"{tmp_path / 'nope.yaml'}: cannot read: No such file or directory"]


def test_yaml_that_is_not_a_mapping_is_refused():
    """Refuse a top-level list, naming the file."""
    with pytest.raises(SpecError, match=r"not_a_mapping\.yaml: expected a mapping with a 'kind' field, got list"):
        load_spec(FIXTURES / "not_a_mapping.yaml")


def test_loaded_specs_are_frozen():
    """Refuse to change a field of a loaded track."""
    track = load_track(ROOT / "tracks" / "oval4.yaml")
    with pytest.raises(ValidationError, match="frozen"):
        track.laps = 3
    assert track.laps == 1


def test_pipeline_track_is_resolved_next_to_the_pipeline_file(tmp_path):
    """Find `track: ../oval4.yaml` relative to the pipeline file, not the working directory."""
    shutil.copy(ROOT / "tracks" / "oval4.yaml", tmp_path / "oval4.yaml")
    (tmp_path / "sub").mkdir()
    path = tmp_path / "sub" / "p.yaml"
    path.write_text("kind: pipeline\nname: p\ntrack: ../oval4.yaml\nstages:\n  - {name: solo, iterations: 1}\n")
    spec, track = load_pipeline(path)
    assert (spec.name, track.name, len(track.gates)) == ("p", "oval4", 4)


def test_pipeline_with_a_broken_track_names_the_track_file(tmp_path):
    """Report the referenced track's file and bad field when the pipeline itself is fine."""
    bad = FIXTURES / "unknown_key.yaml"
    path = tmp_path / "p.yaml"
    path.write_text(f"kind: pipeline\nname: p\ntrack: {bad}\nstages:\n  - {{name: solo, iterations: 1}}\n")
    with pytest.raises(SpecError) as info:
        load_pipeline(path)
    assert info.value.problems == [f"{bad}: gates.0.colour: Extra inputs are not permitted"]


def test_a_pipeline_of_an_older_version_is_refused_naming_what_changed(tmp_path):
    """A version-1 file (with the field since renamed) gets one line: its version, this one, and the renames."""
    path = tmp_path / "p.yaml"
    path.write_text(f"kind: pipeline\nversion: 1\nname: p\ntrack: {ROOT / 'tracks' / 'oval4.yaml'}\nstages:\n"
                    "  - {name: solo, iterations: 1}\n"
                    "  - {name: 2v2, scenario: 2v2, selfplay: {promotion: {formats: true}}}\n")
    with pytest.raises(SpecError) as info:
        load_pipeline(path)
    [problem] = info.value.problems
    assert problem.startswith(f"{path}: version: the file is version 1, this spiral reads version 2")
    assert "selfplay.promotion.formats is now selfplay.promotion.scenarios" in problem


@pytest.mark.parametrize("version", [3, "two"])
def test_a_pipeline_of_a_version_this_spiral_does_not_know_is_refused(tmp_path, version):
    path = tmp_path / "p.yaml"
    path.write_text(f"kind: pipeline\nversion: {version}\nname: p\ntrack: {ROOT / 'tracks' / 'oval4.yaml'}\n"
                    "stages:\n  - {name: solo, iterations: 1}\n")
    with pytest.raises(SpecError, match="is not a version this spiral reads"):
        load_pipeline(path)

"""The command line: exit codes, error lines, written files."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from spiral.cli import app
from spiral.config import SpecError
from spiral.core.errors import UsageError

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()


def test_validate_exits_zero_for_the_shipped_tracks():
    """Print one OK line per valid file and exit 0."""
    tracks = sorted(str(p) for p in (ROOT / "tracks").glob("*.yaml"))
    result = runner.invoke(app, ["validate", *tracks])
    assert result.exit_code == 0
    assert result.output.count("OK ") == len(tracks)


def test_validate_exits_one_with_field_naming_errors():
    """Print `Error: <file>: <field>: ...` for a malformed file and exit 1, without a traceback."""
    bad = ROOT / "tests" / "config" / "fixtures" / "unknown_key.yaml"
    result = runner.invoke(app, ["validate", str(ROOT / "tracks" / "oval4.yaml"), str(bad)])
    assert result.exit_code == 1
    assert f"Error: {bad}: gates.0.colour:" in result.output
    assert "Traceback" not in result.output


def test_schema_writes_one_json_schema_per_kind(tmp_path):
    """Write track and pipeline schemas that list their required fields."""
    result = runner.invoke(app, ["schema", "--out", str(tmp_path)])
    assert result.exit_code == 0
    track = json.loads((tmp_path / "track.schema.json").read_text())
    assert {"kind", "name", "gates", "start", "bounds"} <= set(track["required"])
    assert "stages" in json.loads((tmp_path / "pipeline.schema.json").read_text())["properties"]


def test_track_show_writes_a_png(tmp_path):
    """Draw circuit6 into a PNG of plausible size."""
    out = tmp_path / "c6.png"
    result = runner.invoke(app, ["track", "show", str(ROOT / "tracks" / "circuit6.yaml"), "--out", str(out)])
    assert result.exit_code == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert out.stat().st_size > 10_000


def test_track_info_reports_gates_and_centreline(tmp_path):
    """Report the gate count and the centreline length in text and JSON."""
    out = tmp_path / "info.json"
    result = runner.invoke(app, ["track", "info", str(ROOT / "tracks" / "oval4.yaml"), "--json", str(out)])
    assert result.exit_code == 0
    info = json.loads(out.read_text())
    assert info["gate_count"] == 4
    assert "4 gates" in result.output
    assert abs(info["centreline_length_m"] - 4 * (3.0**2 + 2.0**2) ** 0.5) < 1e-9


def test_eval_reports_a_missing_checkpoint_as_an_error():
    """Exit 1 with an `Error:` line naming the checkpoint."""
    result = runner.invoke(app, ["eval", "--track", str(ROOT / "tracks" / "oval4.yaml"), "--method", "x=/nope.pt"])
    assert result.exit_code == 1
    assert "Error: /nope.pt: no such checkpoint" in result.output


def test_validate_checks_the_track_a_pipeline_names(tmp_path):
    """Fail a valid pipeline whose track overlaps two gates, naming the track file and field on stderr."""
    bad = ROOT / "tests" / "config" / "fixtures" / "overlapping_gates.yaml"
    path = tmp_path / "p.yaml"
    path.write_text(f"kind: pipeline\nname: p\ntrack: {bad}\nstages:\n  - {{name: solo, iterations: 1}}\n")
    result = runner.invoke(app, ["validate", str(path)])
    assert result.exit_code == 1
    assert result.stderr.startswith(f"Error: {bad}: gates.1.position: ")
    assert "OK" not in result.stdout


def test_track_show_reports_a_malformed_track_without_a_traceback(tmp_path):
    """Print `Error: <file>: <field>: ...`, exit 1 and write no image."""
    bad = ROOT / "tests" / "config" / "fixtures" / "unknown_key.yaml"
    out = tmp_path / "bad.png"
    result = runner.invoke(app, ["track", "show", str(bad), "--out", str(out)])
    assert result.exit_code == 1
    assert result.stderr == f"Error: {bad}: gates.0.colour: Extra inputs are not permitted\n"
    assert not out.exists()


def test_track_info_lists_every_gate_of_circuit6():
    """Print the centreline length and one line per gate with its passing direction."""
    result = runner.invoke(app, ["track", "info", str(ROOT / "tracks" / "circuit6.yaml")])
    assert result.exit_code == 0
    assert "6 gates, centreline 14.48 m" in result.stdout
    gate_lines = [line for line in result.stdout.splitlines() if line.startswith("  gate ")]
    assert len(gate_lines) == 6 and all("passing [" in line for line in gate_lines)


def test_bench_ppo_profiles_a_smoke_stage_and_names_an_unknown_stage(tmp_path):
    """Print the rollout and update split and write the JSON; an unknown stage is refused with the file's name."""
    out = tmp_path / "ppo.json"
    smoke = str(ROOT / "pipelines" / "smoke.yaml")
    result = runner.invoke(app, ["bench", "ppo", smoke, "--stage", "solo", "--worlds", "4", "--iterations", "1",
                                 "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert "samples per iteration" in result.output and "matmul limit" in result.output
    data = json.loads(out.read_text())
    assert data["worlds"] == 4 and data["samples_per_iteration"] == 4 * 8
    bad = runner.invoke(app, ["bench", "ppo", smoke, "--stage", "nope"])
    assert bad.exit_code == 1 and "Error: --stage:" in bad.output and "no stage named 'nope'" in bad.output
    missing = runner.invoke(app, ["bench", "ppo", smoke, "--stage", "1v1", "--checkpoints-dir", str(tmp_path)])
    assert missing.exit_code == 1 and f"--init: {tmp_path / 'smoke' / 'solo' / 'best.pt'} does not exist" in \
        missing.output


def test_bench_kernels_prints_a_row_per_kernel_and_writes_the_json(tmp_path):
    """`spiral bench kernels` at a tiny size: a table row per kernel of a control step, the same numbers as JSON."""
    out = tmp_path / "kernels.json"
    result = runner.invoke(app, ["bench", "kernels", "--worlds", "2", "--drones", "2", "--launches", "2",
                                 "--repeats", "1", "--json", str(out)])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    assert (data["worlds"], data["drones"], data["launches"]) == (2, 2, 2)
    assert [f"`{r['kernel']}`" in result.output for r in data["kernels"]] == [True] * 6
    assert "2 worlds × 2 drones" in result.output


def test_sim_threads_option_sets_the_simulators_thread_count_and_refuses_zero(monkeypatch):
    """--sim-threads 2 reaches the profiled worlds, which step on two shares of worlds; 0 is a usage error."""
    from spiral.sim import World

    shares = []
    init = World.__init__

    def recording_init(self, *args, **kwargs):
        init(self, *args, **kwargs)
        shares.append(len(self._shards))

    monkeypatch.setattr(World, "__init__", recording_init)
    smoke = str(ROOT / "pipelines" / "smoke.yaml")
    result = runner.invoke(app, ["bench", "ppo", smoke, "--stage", "solo", "--worlds", "4", "--iterations", "1",
                                 "--sim-threads", "2"])
    assert result.exit_code == 0, result.output
    assert shares and set(shares) == {2}
    bad = runner.invoke(app, ["bench", "ppo", smoke, "--sim-threads", "0"])
    assert bad.exit_code == 2 and "--sim-threads" in bad.output


def test_status_lines_up_every_steps_state_after_the_longest_step_name(tmp_path):
    """With the planner's pairing steps (the longest names), each state still starts in one column."""
    smoke = (ROOT / "pipelines" / "smoke.yaml").read_text().replace("../tracks/", str(ROOT / "tracks") + "/")
    path = tmp_path / "smoke.yaml"
    path.write_text(smoke + "report: {se_ibr: true}\n")
    result = runner.invoke(app, ["status", str(path), "--runs-dir", str(tmp_path / "runs"),
                                 "--checkpoints-dir", str(tmp_path / "ckpt")])
    assert result.exit_code == 0, result.output
    lines = [line for line in result.output.splitlines() if line.endswith("missing")]
    names = [line.split()[0] for line in lines]
    assert "eval:se-ibr-vs-2v2-noselfplay" in names and names[-1] == "report"
    assert len({line.index("missing") for line in lines}) == 1


def test_status_with_overrides_names_the_variants_run_and_refuses_a_wrong_one_in_one_line(tmp_path):
    """`spiral status --set seed=1 --json` reports the run `full-seed-1` with its overrides; a misspelt field is one
    `Error:` line naming the file, the override and the field."""
    full, dirs = ROOT / "pipelines" / "full.yaml", ["--runs-dir", str(tmp_path / "runs"),
                                                  "--checkpoints-dir", str(tmp_path / "ckpt")]
    result = runner.invoke(app, ["status", str(full), "--set", "seed=1", "--json", str(tmp_path / "s.json"), *dirs])
    assert result.exit_code == 0, result.output
    described = json.loads((tmp_path / "s.json").read_text())
    assert described["pipeline"] == "full-seed-1" and described["overrides"] == ["seed=1"]
    bad = runner.invoke(app, ["status", str(full), "--set", "stages.1v1.iteratoins=5", *dirs])
    assert bad.exit_code == 1
    assert f"Error: {full} with --set stages.1v1.iteratoins=5: stages.1.iteratoins" in bad.output


def test_debug_shows_the_traceback_of_an_error_printed_as_one_line_without_it(tmp_path, monkeypatch):
    """A malformed track file is one `Error:` line; under `spiral --debug` the same error keeps its traceback."""
    monkeypatch.setenv("SPIRAL_DEBUG", "0")  # restored after the test, which --debug sets
    bad = ROOT / "tests" / "config" / "fixtures" / "unknown_key.yaml"
    plain = runner.invoke(app, ["track", "info", str(bad)])
    assert plain.exit_code == 1 and f"Error: {bad}: gates.0.colour:" in plain.output
    assert plain.exception is None or isinstance(plain.exception, SystemExit)
    debug = runner.invoke(app, ["--debug", "track", "info", str(bad)])
    assert debug.exit_code == 1 and isinstance(debug.exception, SpecError)
    assert "Error:" not in debug.output


def test_an_error_that_is_not_the_users_keeps_its_traceback(monkeypatch):
    """A ValueError from inside spiral (a bug, not a UsageError) is not hidden behind an `Error:` line."""
    monkeypatch.setenv("SPIRAL_DEBUG", "0")  # restored after the test, which --debug sets

    def broken(*args, **kwargs):
        raise ValueError("an internal inconsistency")

    monkeypatch.setattr("spiral.eval.evaluate.evaluate_methods", broken)
    result = runner.invoke(app, ["eval", "--track", str(ROOT / "tracks" / "oval4.yaml"), "--method", "se-ibr",
                                 "--runs", "1"])
    assert isinstance(result.exception, ValueError) and not isinstance(result.exception, UsageError)
    assert "Error:" not in result.output


def test_report_refuses_a_racing_section_without_held_out_placements(tmp_path):
    """`spiral report --racing-laps 3` races the held-out placements: without --holdout-runs it is one Error line."""
    result = runner.invoke(app, ["report", str(tmp_path), "--racing-laps", "3", "--track",
                                 str(ROOT / "tracks" / "oval4.yaml")])
    assert result.exit_code == 1
    assert "Error: the racing section races the held-out placements" in result.output

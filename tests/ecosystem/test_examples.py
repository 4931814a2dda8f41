"""The scripts in examples/ run as written (in this process, to skip a second import of torch and Warp)."""

from __future__ import annotations

import json
import re
import runpy
import sys
import tempfile
from pathlib import Path

import pytest
import torch

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture
def script_env(monkeypatch, tmp_path):
    """Run a script with no arguments, its temporary files under tmp_path, and torch's thread count restored."""
    monkeypatch.setattr(sys, "argv", ["example"])
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    threads = torch.get_num_threads()
    yield tmp_path
    torch.set_num_threads(threads)


def test_train_custom_track_trains_saves_and_races(script_env, capsys):
    """Train 5 iterations on the Python-defined track, write best.pt and race 16 worlds."""
    runpy.run_path(str(EXAMPLES / "train_custom_track.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "trained 5 iterations, 2560 env steps" in out
    assert list(script_env.glob("spiral-example-*/best.pt"))
    success = float(re.search(r"success (\d\.\d\d)", out).group(1))
    assert 0.0 <= success <= 1.0


def test_gym_loop_steps_the_vector_and_the_single_env(script_env, capsys):
    """Step 8 drones for 200 steps and fly one single-env episode to its end."""
    runpy.run_path(str(EXAMPLES / "gym_loop.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "vector env: 8 drones, observation (78,)" in out and "autoreset SameStep" in out
    assert re.search(r"200 steps: \d+ episodes ended", out)
    assert re.search(r"single env: episode of \d+ steps", out)


def test_stage_variant_trains_an_overridden_stage_and_evaluates_it(script_env, monkeypatch, capsys):
    """Override the smoke pipeline's 1v1 stage (mirror self-play only), train it from a solo policy, evaluate."""
    from spiral.config import load_pipeline, resolve_airframe
    from spiral.env import RaceSetting
    from spiral.selfplay import StageSources, run_stage

    pipeline = EXAMPLES.parent / "pipelines" / "smoke.yaml"
    spec, track = load_pipeline(pipeline)
    run_stage(RaceSetting(track, resolve_airframe(spec.airframe), spec.sim), spec.stages[0], script_env / "solo",
              sources=StageSources(pool_dir=script_env / "unused"), progress=False)
    out = script_env / "variant"
    monkeypatch.setattr(sys, "argv", ["stage_variant.py", str(pipeline), "1v1", str(script_env / "solo" / "best.pt"),
                                      str(out), "--set", "selfplay.p_self=1.0", "--set", "iterations=1"])
    runpy.run_path(str(EXAMPLES / "stage_variant.py"), run_name="__main__")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["overrides"] == ["selfplay.p_self=1.0", "iterations=1"]
    assert 0.0 <= summary["success_ratio"] <= 1.0
    assert set(summary["crashes"]) == {"ground", "bounds", "gate", "drone", "timeout"} and (out / "best.pt").exists()
    assert len((out / "train_log.jsonl").read_text().splitlines()) == 1  # the iterations override took effect
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == summary

    # --pool-from: the first variant's pool joins a second variant's opponents beside its own line
    from spiral.core.files import file_sha256
    from spiral.selfplay.pool import Pool

    foreign = Pool(out / "pool").members
    second = script_env / "variant-2"
    argv = ["stage_variant.py", str(pipeline), "1v1", str(script_env / "solo" / "best.pt"), str(second),
            "--pool-from", str(out / "pool"), "--set", "iterations=1"]
    monkeypatch.setattr(sys, "argv", argv)
    runpy.run_path(str(EXAMPLES / "stage_variant.py"), run_name="__main__")
    pool = Pool(second / "pool")
    (init,) = [m for m in pool.members if m.stage == "init"]
    assert init.sha256 == foreign[0].sha256  # both variants start from the same solo best
    assert not pool.member(pool.latest_best).stage.endswith("-from1")  # the learner's own line stays the latest
    copied = [m for m in pool.members if m.stage.endswith("-from1")]
    assert [(m.stage, m.iteration, m.sha256) for m in copied] == [(m.stage + "-from1", m.iteration, m.sha256)
                                                                   for m in foreign]
    monkeypatch.setattr(sys, "argv", argv)  # a rerun into the same folder copies nothing twice
    runpy.run_path(str(EXAMPLES / "stage_variant.py"), run_name="__main__")
    assert len(Pool(second / "pool").members) == len(pool.members)

    # --first-opponent: a checkpoint goes in front of the pool copied beside the init policy (the member p_first draws)
    first = script_env / "variant-3"
    init_pool, solo_sha = Pool(out / "pool"), file_sha256(script_env / "solo" / "best.pt")
    argv = ["stage_variant.py", str(pipeline), "1v1", str(out / "best.pt"), str(first),
            "--first-opponent", str(script_env / "solo" / "best.pt"), "--set", "iterations=1"]
    for _ in range(2):  # the rerun into the same folder adds nothing
        monkeypatch.setattr(sys, "argv", argv)
        runpy.run_path(str(EXAMPLES / "stage_variant.py"), run_name="__main__")
        pool = Pool(first / "pool")
        assert pool.members[0].stage == "first" and pool.members[0].sha256 == solo_sha
        assert [m.sha256 for m in pool.members[1:1 + len(init_pool.members)]] == [m.sha256 for m in init_pool.members]
        assert [m.stage for m in pool.members].count("first") == 1
        assert pool.member(pool.latest_best).stage != "first"


def test_separation_probe_races_a_policy_with_each_filter_setting(script_env, policy_checkpoint, monkeypatch, capsys):
    """Self-match with no filter and with one, then cross-play against itself: one line per setting."""
    track = str(EXAMPLES.parent / "tracks" / "circuit6.yaml")
    base = ["separation_probe.py", str(policy_checkpoint), "2v2", "--track", track, "--runs", "4", "--seed", "3"]
    monkeypatch.setattr(sys, "argv", [*base, "--filter", "none", "--filter", "0.25,0.4,1.5"])
    runpy.run_path(str(EXAMPLES / "separation_probe.py"), run_name="__main__")
    lines = capsys.readouterr().out.strip().splitlines()[-2:]
    assert [line.split(":")[0].strip() for line in lines] == ["none", "0.25,0.4,1.5"]
    assert all(0.0 <= float(re.search(r"success (\d\.\d+)", line).group(1)) <= 1.0 for line in lines)
    monkeypatch.setattr(sys, "argv", [*base, "--against", str(policy_checkpoint), "--filter", "0.3,0.2,1.0"])
    runpy.run_path(str(EXAMPLES / "separation_probe.py"), run_name="__main__")
    line = capsys.readouterr().out.strip().splitlines()[-1]
    shares = [float(x) for x in re.search(r"win (\S+) loss (\S+) draw (\S+)", line).groups()]
    assert line.startswith("0.3,0.2,1.0") and abs(sum(shares) - 1.0) < 2e-3


def test_crossplay_leads_accounts_for_every_lost_lead(script_env, policy_checkpoint, monkeypatch, capsys):
    """A policy raced against itself: rates sum to one, and each team's lost leads are at most its leads."""
    track = str(EXAMPLES.parent / "tracks" / "circuit6.yaml")
    monkeypatch.setattr(sys, "argv", ["crossplay_leads.py", str(policy_checkpoint), str(policy_checkpoint), "1v1",
                                      "--track", track, "--runs", "4", "--seed", "3", "--passage", "0"])
    runpy.run_path(str(EXAMPLES / "crossplay_leads.py"), run_name="__main__")
    lines = capsys.readouterr().out.strip().splitlines()[-5:]
    shares = [float(x) for x in re.search(r"win (\S+) loss (\S+) draw (\S+)", lines[0]).groups()]
    assert abs(sum(shares) - 1.0) < 2e-3
    for line in (lines[1], lines[3]):
        leads, lost, by_crash = (int(x) for x in re.search(r"in (\d+), loses (\d+) of them, (\d+) with", line).groups())
        assert 0 <= by_crash <= lost <= leads <= 4
    assert all(re.search(r"crashes of 4 drones", line) for line in (lines[2], lines[4]))

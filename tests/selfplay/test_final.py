"""A stage's final pick: every promoted policy races validation self-matches, the best becomes `best.pt`; its
placements may not be ones the pipeline reports on."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from spiral.config import PipelineSpec, SimCfg, StageSpec
from spiral.env.setting import RaceSetting
from spiral.selfplay import StageSources, run_stage
from spiral.selfplay.final import FINAL_PICK_FILE, Candidate, _validation_envs, rank_candidates, validation_success
from tests.selfplay.helpers import CF2X, COMMON, PERMISSIVE, SOLO

ROOT = Path(__file__).resolve().parents[2]


def test_the_candidate_with_the_highest_mean_success_wins_and_a_tie_goes_to_the_later():
    early = Candidate(Path("a.pt"), 24, {"box-1v1": 1.0, "track-1v1": 0.5})
    late = Candidate(Path("b.pt"), 99, {"box-1v1": 0.75, "track-1v1": 0.75})
    best = Candidate(Path("c.pt"), 49, {"box-1v1": 1.0, "track-1v1": 0.75})
    assert late.score == pytest.approx(0.75)
    assert rank_candidates([early, late]) is late  # equal means: the later
    assert rank_candidates([early, best, late]) is best


@pytest.mark.bitwise
def test_every_candidate_races_the_same_validation_placements(line2):
    """Two candidates race each validation self-match from the same start states (a paired comparison), not from
    the next placements of the env's generator."""
    stage = StageSpec.model_validate({"name": "1v1", "scenario": "1v1", "iterations": 1, "mix": {"solo": 0.25},
                                      **COMMON, "selection": {"final": {"laps": 1, "races": 3, "seed": 5}}})
    envs = _validation_envs(stage, RaceSetting(line2, CF2X, SimCfg()), stage.selection.final, device="cpu")
    placements = {key: env.generator.get_state() for key, env in envs.items()}
    seen: list[dict[str, torch.Tensor]] = []
    for _ in range(2):
        first: dict[str, torch.Tensor] = {}
        for key, env in envs.items():
            def hover(obs, key=key, env=env, first=first):
                first.setdefault(key, env.pos.clone())
                return torch.zeros(obs["policy"].shape[0], 4)
            validation_success({key: env}, placements, hover)
        seen.append(first)
    assert set(seen[0]) == {"box-1v1", "track-1v1", "box-solo", "track-solo"}
    for key in seen[0]:
        torch.testing.assert_close(seen[1][key], seen[0][key], rtol=0, atol=0)  # exact: the same draws
    envs["box-1v1"].reset()  # the env's own next draw would have started elsewhere
    assert (envs["box-1v1"].pos - seen[0]["box-1v1"]).abs().max() > 0.01


def test_a_stage_with_a_final_pick_keeps_every_promoted_policy_and_publishes_the_one_that_races_best(line2, tmp_path):
    """A 1v1 stage mixing in solo worlds, promoting at every check, keeps a copy of each promoted policy; its final
    pick races the latest two in 1v1 and solo self-matches from the box and from track starts over two laps, writes
    the one with the highest mean success (ties: the later) as `best.pt` and records both."""
    setting = RaceSetting(line2, CF2X, SimCfg())
    solo = StageSpec.model_validate({"name": "solo", "iterations": 1, **SOLO})
    run_stage(setting, solo, tmp_path / "solo", sources=StageSources(pool_dir=tmp_path / "pool"), progress=False)
    duel = StageSpec.model_validate({
        "name": "1v1", "scenario": "1v1", "iterations": 3, "mix": {"solo": 0.25}, "selfplay": PERMISSIVE,
        **COMMON, "selection": {"final": {"laps": 2, "races": 4, "seed": 5, "candidates": 2}}})
    run_dir = tmp_path / "duel"
    result = run_stage(setting, duel, run_dir, sources=StageSources(
        pool_dir=tmp_path / "pool-duel", init_checkpoint=tmp_path / "solo" / "best.pt"), progress=False)
    record = json.loads((run_dir / FINAL_PICK_FILE).read_text())
    promoted = sorted((run_dir / "promoted").glob("best-*.pt"))
    assert len(promoted) >= 3  # every check promotes; only the latest two race
    assert [c["iteration"] for c in record["candidates"]] == [int(p.stem.split("-")[1]) for p in promoted[-2:]]
    assert (record["laps"], record["races"], record["seed"]) == (2, 4, 5)
    for c in record["candidates"]:
        assert set(c["success"]) == {"box-1v1", "track-1v1", "box-solo", "track-solo"}
    top = max((c["score"], c["iteration"]) for c in record["candidates"])
    assert record["chosen"] == top[1] == result.best.iteration
    chosen = run_dir / "promoted" / f"best-{record['chosen']:05d}.pt"
    assert (run_dir / "best.pt").read_bytes() == chosen.read_bytes()


def test_a_final_pick_on_the_placements_the_pipeline_reports_on_is_refused():
    data = {"kind": "pipeline", "name": "p", "track": str(ROOT / "tracks" / "oval4.yaml"),
            "evaluation": {"runs": 8, "seed": 0, "holdout_runs": 16, "holdout_seed": 1},
            "stages": [{"name": "solo", "iterations": 1},
                       {"name": "1v1", "scenario": "1v1", "iterations": 1, "selection": {"final": {"seed": 1}}}]}
    with pytest.raises(ValueError, match=r"stages\.1\.selection\.final\.seed: 1 is a seed the pipeline reports on"):
        PipelineSpec.model_validate(data)
    data["stages"][1]["selection"]["final"]["seed"] = 2
    assert PipelineSpec.model_validate(data).stages[1].selection.final.seed == 2

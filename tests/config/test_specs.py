"""Specs: shipped files validate, malformed files fail naming file and field, geometry conventions hold."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from spiral.config import (
    AIRFRAMES,
    AirframeSel,
    SpecError,
    StageSpec,
    gate_rotation,
    load_pipeline,
    load_spec,
    load_track,
    resolve_airframe,
)

ROOT = Path(__file__).resolve().parents[2]
FIXTURES = Path(__file__).parent / "fixtures"

MALFORMED = {
    "unknown_key.yaml": "gates.0.colour",
    "wrong_kind.yaml": "kind",
    "string_for_number.yaml": "gates.0.position.1",
    "nan.yaml": "gates.0.position.2",
    "one_gate.yaml": "gates",
    "gate_outside_bounds.yaml": "gates.1.position",
    "overlapping_gates.yaml": "gates.1.position",
    "negative_opening.yaml": "opening",
    "yaml_syntax.yaml": "line 5",
    "pipeline_bad_field.yaml": "stages.0.ppo.learning_rate",
    "pipeline_bad_override.yaml": "airframe.overrides.mas",
    "pipeline_bad_separation.yaml": "stages.0.env.action.separation.horizon_s",
}


@pytest.mark.parametrize("path", sorted((ROOT / "tracks").glob("*.yaml")) + sorted((ROOT / "pipelines").glob("*.yaml")),
                         ids=lambda p: p.name)
def test_every_shipped_spec_validates(path):
    """Load every track and pipeline shipped in the repository."""
    spec = load_pipeline(path)[0] if path.parent.name == "pipelines" else load_track(path)
    assert spec.name


@pytest.mark.parametrize(("name", "field"), sorted(MALFORMED.items()))
def test_malformed_spec_names_the_file_and_the_field(name, field):
    """Fail with one line per problem that starts with the file and names the bad field."""
    with pytest.raises(SpecError) as info:
        load_pipeline(FIXTURES / name) if name.startswith("pipeline") else load_spec(FIXTURES / name)
    line = info.value.problems[0]
    assert line.startswith(str(FIXTURES / name) + ":")
    assert f": {field}" in line


def test_wrong_kind_for_the_expected_spec_is_refused():
    """Refuse a track file where a pipeline is expected."""
    with pytest.raises(SpecError, match="kind: expected 'pipeline', got 'track'"):
        load_pipeline(ROOT / "tracks" / "circuit6.yaml")


def test_gate_rotation_is_rz_ry_rx():
    """Compose yaw 90 after pitch 90: the local x axis (normal) points straight down."""
    rot = gate_rotation((0.0, 90.0, 90.0))
    assert np.allclose(rot[:, 0], [0.0, 0.0, -1.0], atol=1e-12)
    assert np.allclose(rot[:, 1], [-1.0, 0.0, 0.0], atol=1e-12)
    assert np.allclose(gate_rotation((30.0, 0.0, 0.0))[:, 2], [0.0, -0.5, math.sqrt(3) / 2])


def test_inferred_directions_give_a_flyable_order_on_circuit6(circuit6):
    """Point every gate's passing direction from the previous gate towards the next one."""
    c, fwd = circuit6.gate_centers(), circuit6.gate_forward()
    for i in range(len(c)):
        assert fwd[i] @ (c[(i + 1) % len(c)] - c[i - 1]) > 0
    assert circuit6.gate_directions().tolist() == [-1, -1, -1, -1, 1, -1]


def test_centreline_length_is_the_closed_polyline_length(circuit6):
    """Sum the distances between consecutive gate centres around the loop."""
    c = circuit6.gate_centers()
    expected = sum(np.linalg.norm(c[(i + 1) % 6] - c[i]) for i in range(6))
    assert circuit6.centreline_length() == pytest.approx(expected)


def test_airframe_override_changes_one_field_and_typos_fail():
    """Apply a valid override field by field; name a misspelt override key in the error."""
    heavy = resolve_airframe(AirframeSel(overrides={"mass": 0.03, "pid": {"max_tilt_deg": 45.0}}))
    assert heavy.mass == pytest.approx(0.03) and heavy.pid.max_tilt_deg == pytest.approx(45.0)
    assert heavy.pid.pos_p == AIRFRAMES["cf2x"].pid.pos_p
    with pytest.raises(SpecError, match=r"airframe\.overrides\.mas"):
        resolve_airframe(AirframeSel(overrides={"mas": 0.03}))


def test_max_rpm_gives_the_thrust_to_weight_ratio():
    """Make four motors at max rpm lift thrust_to_weight times the weight."""
    cf = AIRFRAMES["cf2x"]
    assert 4 * cf.kf * cf.max_rpm**2 == pytest.approx(cf.thrust_to_weight * cf.mass * 9.81)
    assert 4 * cf.kf * cf.hover_rpm**2 == pytest.approx(cf.mass * 9.81)


def test_stage_budget_comes_from_iterations_or_env_steps():
    """Derive iterations from an env-step budget and refuse both budgets at once."""
    stage = StageSpec(name="s", worlds=100, env_steps=10_000, ppo={"num_steps_per_env": 24})
    assert stage.iteration_budget() == 5
    with pytest.raises(ValueError, match="iterations"):
        StageSpec(name="s", iterations=3, env_steps=10)


def oval_pipeline(tmp_path, body: str):
    """A pipeline file on oval4 whose stages and settings are ``body`` (YAML)."""
    path = tmp_path / "p.yaml"
    path.write_text(f"kind: pipeline\nname: p\ntrack: {ROOT / 'tracks' / 'oval4.yaml'}\n{body}")
    return path


def test_pipeline_refuses_unknown_init_stage(tmp_path):
    """Name the stage field when init_from points at no earlier stage."""
    path = oval_pipeline(tmp_path, "stages:\n  - {name: a, iterations: 1}\n"
                                   "  - {name: b, iterations: 1, init_from: zz}\n")
    with pytest.raises(SpecError, match=r"stages\.1\.init_from"):
        load_pipeline(path)


def test_pipeline_refuses_a_frozen_opponent_from_no_earlier_stage(tmp_path):
    """Name selfplay.opponent_from when it points at a later stage or none."""
    for source in ("c", "zz"):
        path = oval_pipeline(tmp_path, "stages:\n  - {name: a, iterations: 1}\n"
                                       "  - {name: b, scenario: 1v1, iterations: 1, selfplay: {mode: frozen, "
                                       f"opponent_from: {source}}}}}\n  - {{name: c, iterations: 1}}\n")
        with pytest.raises(SpecError, match=r"stages\.1\.selfplay\.opponent_from"):
            load_pipeline(path)


def test_pipeline_refuses_held_out_placements_on_the_evaluation_seed(tmp_path):
    """Name evaluation.holdout_seed when the held-out check would race the protocol's own placements."""
    path = oval_pipeline(tmp_path, "stages:\n  - {name: a, iterations: 1}\n"
                                   "evaluation: {seed: 3, holdout_runs: 64, holdout_seed: 3}\n")
    with pytest.raises(SpecError, match=r"evaluation.*holdout_seed"):
        load_pipeline(path)


def test_pipeline_names_evaluation_sides_when_it_is_not_a_head_to_head_protocol(tmp_path):
    """Accept 'a' and 'both' (the default) for evaluation.sides; name the field for anything else."""
    stages = "stages:\n  - {name: a, iterations: 1}\n"
    assert load_pipeline(oval_pipeline(tmp_path, stages))[0].evaluation.sides == "both"
    assert load_pipeline(oval_pipeline(tmp_path, stages + "evaluation: {sides: a}\n"))[0].evaluation.sides == "a"
    with pytest.raises(SpecError, match=r"evaluation\.sides"):
        load_pipeline(oval_pipeline(tmp_path, stages + "evaluation: {sides: swapped}\n"))


@pytest.mark.parametrize("name", ["full.yaml", "smoke.yaml", "paper.yaml"])
def test_shipped_baseline_stages_match_their_self_play_stage_but_for_the_opponents(name):
    """PPO without self-play is an ablation: same env (reward, observation, actions), PPO and budget per format; it
    races every format mixed into its twin stage that it races at all, with the same share (it may keep fewer)."""
    stages = load_pipeline(ROOT / "pipelines" / name)[0].stages
    frozen = [s for s in stages if s.selfplay.mode == "frozen"]
    assert {s.scenario for s in frozen} == {"1v1", "2v2"}
    for stage in frozen:
        twins = [s for s in stages if s.scenario == stage.scenario and s.selfplay.mode == "pool"]
        assert len(twins) == 1, f"{stage.name}: expected one self-play stage of format {stage.scenario}"
        twin = twins[0]
        assert stage.env == twin.env, stage.name
        assert stage.ppo == twin.ppo, stage.name
        assert (stage.worlds, stage.iteration_budget()) == (twin.worlds, twin.iteration_budget()), stage.name
        assert stage.mix.items() <= twin.mix.items(), stage.name
        assert stage.selfplay.promotion == twin.selfplay.promotion, stage.name


def test_the_shipped_pipeline_mixes_2v2_worlds_into_spirals_1v1_stage_but_not_the_baselines():
    """full.yaml: SPIRAL's 1v1 stage races 30% 2v2 worlds; the baseline's 1v1 stage keeps pure 1v1 worlds (its
    stronger setting); both 2v2 stages keep solo and 1v1 worlds, so each branch's final policy races every format."""
    stages = {s.name: s for s in load_pipeline(ROOT / "pipelines" / "full.yaml")[0].stages}
    assert stages["1v1"].mix == pytest.approx({"2v2": 0.3})
    assert stages["1v1-noselfplay"].mix == {}
    assert stages["2v2"].mix == pytest.approx({"solo": 0.05, "1v1": 0.15})
    assert stages["2v2-noselfplay"].mix == pytest.approx({"solo": 0.05, "1v1": 0.15})


@pytest.mark.parametrize(("options", "field"), [
    ({"selfplay": {"p_self": 0.5}}, "selfplay"),
    ({"env": {"reward": {"win": 3.0}}}, "env.reward.win"),
    ({"env": {"reward": {"proximity": 0.1}}}, "env.reward.proximity"),
], ids=["selfplay", "outcome", "proximity"])
def test_a_solo_stage_refuses_options_that_act_on_other_drones(tmp_path, options, field):
    """Options that need other drones make no sense in a solo stage: the error names the stage and the field."""
    path = tmp_path / "p.yaml"
    stage = {"name": "solo", "scenario": "solo", "iterations": 1, **options}
    path.write_text(json.dumps({"kind": "pipeline", "name": "p", "track": str(ROOT / "tracks" / "oval4.yaml"),
                                "stages": [stage]}))
    with pytest.raises(SpecError, match=rf"stages\.0.*{field}"):
        load_pipeline(path)


def test_a_stage_setting_the_removed_critic_option_is_refused_as_an_unknown_field(tmp_path):
    """``env.critic`` (a centralised critic, tried and not adopted) is gone; the critic sees the policy's inputs."""
    path = oval_pipeline(tmp_path, "stages:\n  - {name: a, scenario: 1v1, iterations: 1, env: {critic: race}}\n")
    with pytest.raises(SpecError, match=r"stages\.0\.env\.critic: Extra inputs are not permitted"):
        load_pipeline(path)


def test_the_shipped_pipeline_trains_every_multi_drone_stage_with_the_bound_loss_and_the_solo_stage_without():
    """full.yaml: both branches' multi-drone stages keep their mean actions inside the clamped range (bound loss 0.5);
    the solo stage, whose policy both branches start from, trains as before."""
    stages = {s.name: s for s in load_pipeline(ROOT / "pipelines" / "full.yaml")[0].stages}
    assert {name: s.ppo.bound_loss_coef for name, s in stages.items()} == pytest.approx({
        "solo": 0.0, "1v1": 0.5, "2v2": 0.5, "1v1-noselfplay": 0.5, "2v2-noselfplay": 0.5})


def test_the_shipped_pipeline_charges_closing_in_both_branches_and_blinds_only_spirals_opponents():
    """full.yaml: every multi-drone stage of both branches pays for flying into the nearest drone (the same reward for
    the ablation); only SPIRAL's self-play flies blind opponents; both 2v2 stages (which publish the final policies)
    promote only a learner that keeps up in every format of their mix."""
    stages = {s.name: s for s in load_pipeline(ROOT / "pipelines" / "full.yaml")[0].stages}
    assert {name: s.env.reward.closing for name, s in stages.items()} == pytest.approx({
        "solo": 0.0, "1v1": 0.5, "2v2": 0.5, "1v1-noselfplay": 0.5, "2v2-noselfplay": 0.5})
    assert {name: s.selfplay.opponent_blind for name, s in stages.items() if s.scenario != "solo"} == pytest.approx({
        "1v1": 0.3, "2v2": 0.3, "1v1-noselfplay": 0.0, "2v2-noselfplay": 0.0})
    assert {name: s.selfplay.promotion.scenarios for name, s in stages.items() if s.scenario != "solo"} == {
        "1v1": False, "2v2": True, "1v1-noselfplay": False, "2v2-noselfplay": True}


def test_the_shipped_pipeline_flies_the_papers_stack_and_reports_the_filter_as_an_extra_row():
    """No stage of full.yaml puts a separation filter between policy and PID (training or evaluation); the filter
    appears only as the report's extra row."""
    spec = load_pipeline(ROOT / "pipelines" / "full.yaml")[0]
    assert all(stage.env.action.separation is None for stage in spec.stages)
    assert spec.report.separation is not None


def test_the_shipped_pipeline_races_se_ibr_in_its_tables():
    """full.yaml's report has SE-IBR as a row of both tables (and in the cross-play), not a missing cell."""
    spec = load_pipeline(ROOT / "pipelines" / "full.yaml")[0]
    assert spec.report.enabled and spec.report.se_ibr and spec.report.cross_play


@pytest.mark.parametrize(("options", "field"), [
    ({"selection": {"interval": 5}}, r"selection\.interval.*selfplay\.promotion\.interval"),
    ({"selection": {"races": 8}}, r"selection\.races.*selfplay\.promotion\.races"),
])
def test_a_multi_drone_stage_refuses_selection_options_its_promotion_owns(tmp_path, options, field):
    """Multi-drone stages keep their best by promotion, which owns the interval and the race count of their
    evaluations: the solo stages' selection options are refused there, by field."""
    path = tmp_path / "p.yaml"
    stage = {"name": "duel", "scenario": "1v1", "iterations": 1, **options}
    path.write_text(json.dumps({"kind": "pipeline", "name": "p", "track": str(ROOT / "tracks" / "oval4.yaml"),
                                "stages": [stage]}))
    with pytest.raises(SpecError, match=rf"stages\.0.*{field}"):
        load_pipeline(path)


def test_a_stages_self_match_races_as_many_worlds_as_its_evaluations_owner_says():
    """Solo: ``selection.races``; multi-drone: ``selfplay.promotion.races``, as its head to head."""
    solo = StageSpec(name="s", iterations=1, selection={"races": 8})
    duel = StageSpec(name="d", scenario="1v1", iterations=1, selfplay={"promotion": {"races": 16}})
    assert (solo.eval_races, duel.eval_races) == (8, 16)


def test_a_pipeline_refuses_motor_speed_commands_its_policies_cannot_give(tmp_path):
    """The env drives the PID; a pipeline with ``sim.control_mode: rpm`` is refused when loaded, by field."""
    path = tmp_path / "p.yaml"
    path.write_text(json.dumps({"kind": "pipeline", "name": "p", "track": str(ROOT / "tracks" / "oval4.yaml"),
                                "sim": {"control_mode": "rpm"}, "stages": [{"name": "solo", "iterations": 1}]}))
    with pytest.raises(SpecError, match=r"sim\.control_mode"):
        load_pipeline(path)


def test_the_paper_pipeline_observes_the_papers_814_inputs_and_rewards_its_four_terms_only():
    """paper.yaml: every stage observes the 12-D ego state and K = 50 steps of the 2 nearest opponents', the 2 next
    gates' and its own actions (814 inputs) and commands target positions; its reward has the paper's terms
    only (progress with the gate bonus, collision, alignment, the lap's 100 / T_lap); the self-play stages race the
    newest best, promoted on its head to head alone; no opponent is a mirror copy, offset or blind; every episode
    starts from the start box; PPO has an entropy bonus and no bound loss; no weight average or final pick. The file
    spells each of these: the schema's defaults are the shipped recipe's."""
    import torch

    from spiral.env.observations import ObservationBuilder
    from spiral.env.rewards import REWARD_TERMS

    stages = load_pipeline(ROOT / "pipelines" / "paper.yaml")[0].stages
    paper_terms = {"progress", "gate", "collision", "alignment", "lap"}
    for stage in stages:
        assert ObservationBuilder(stage.env.obs, 2, device=torch.device("cpu")).obs_dim == 814, stage.name
        weights = {name: value for name, value in stage.env.reward.model_dump().items()
                   if name in REWARD_TERMS and value}
        assert set(weights) == paper_terms, stage.name
        assert stage.env.episode.track_start_prob == 0 and stage.env.episode.passage_starts is None, stage.name
        assert stage.env.action.separation is None, stage.name
        assert not stage.mix, stage.name
        assert (stage.ppo.entropy_coef, stage.ppo.bound_loss_coef) == pytest.approx((0.005, 0.0)), stage.name
        assert stage.selection.average == pytest.approx(0.0) and stage.selection.final is None, stage.name
    for stage in (s for s in stages if s.scenario != "solo"):
        draws = stage.selfplay
        assert (draws.mirror_share, draws.opponent_offset, draws.opponent_blind) == pytest.approx((0, 0, 0)), stage.name
        promotion = stage.selfplay.promotion
        assert not promotion.self_match and not promotion.scenarios and not promotion.track_starts, stage.name
    for stage in (s for s in stages if s.selfplay.mode == "pool" and s.scenario != "solo"):
        assert stage.selfplay.p_latest == 1 and stage.selfplay.p_self == 0, stage.name


def test_a_stage_that_spells_nothing_gets_the_shipped_recipes_multi_drone_settings(tmp_path):
    """The schema's defaults are full.yaml's multi-drone settings: a 1v1 stage given only its name, scenario and
    budget observes the compact 55 inputs, pays proximity, closing and the race's outcome, starts episodes from gate
    passages and the track, and trains, selects and races opponents as SPIRAL's 1v1 stage of full.yaml does."""
    import torch

    from spiral.env.observations import ObservationBuilder

    spec = load_pipeline(oval_pipeline(tmp_path, "stages:\n  - {name: solo, iterations: 1}\n"
                                                  "  - {name: 1v1, scenario: 1v1, iterations: 1}\n"))[0]
    bare = spec.stages[1]
    assert ObservationBuilder(bare.env.obs, 2, device=torch.device("cpu")).obs_dim == 55
    reward = bare.env.reward
    assert (reward.proximity, reward.closing, reward.win) == pytest.approx((0.1, 0.5, 3.0))
    assert bare.env.episode.passage_starts is not None and bare.env.episode.track_start_prob == pytest.approx(0.3)
    shipped = {s.name: s for s in load_pipeline(ROOT / "pipelines" / "full.yaml")[0].stages}["1v1"]
    assert (bare.env, bare.ppo, bare.selection, bare.selfplay) == (
        shipped.env, shipped.ppo, shipped.selection, shipped.selfplay)

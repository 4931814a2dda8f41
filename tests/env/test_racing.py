"""Full races (run_races): split times, crash partners, contact fault and bearing, and passes in RaceResults."""

from __future__ import annotations

import pytest
import torch

from spiral.env import run_races
from spiral.env.racing import BEARINGS, contact_bearing
from spiral.eval.metrics import summarize_races
from tests.env.helpers import make_env, place, waypoint_policy


def test_race_results_time_every_gate_passage_and_end_with_the_lap_time(oval2):
    """Split times of a scripted lap rise gate by gate, the last one is the lap time, and the summary averages them."""
    env = make_env(oval2, worlds=2, training=False)
    res = run_races(env, waypoint_policy(env))
    assert res.finished.all()
    splits = res.split_time[:, 0]
    assert splits.shape == (2, env.passes_needed)
    assert (splits[:, 0] > 0).all() and (splits.diff(dim=1) > 0).all()
    assert torch.allclose(splits[:, -1], res.lap_time[:, 0])
    assert summarize_races(res)["split_times"] == pytest.approx(splits.mean(dim=0).tolist())


@pytest.mark.parametrize("partner", [1, 2], ids=["teammate", "opponent"])
def test_race_results_name_the_drone_each_crashed_drone_touched(oval2, partner):
    """Fly drone 0 and one other drone into each other in a 2v2 race: each records the other as its crash partner
    and the crash time; the two hovering drones record none, and the contacts count under the right team."""
    env = make_env(oval2, worlds=1, drones=4, learners=(0, 1), training=False)
    chase = {0: partner, partner: 0}

    def act(idx: torch.Tensor) -> torch.Tensor:
        rows = [(env.pos[chase[int(i)]] - env.pos[i]) / env.cfg.action.pos_scale if int(i) in chase
                else torch.zeros(3) for i in idx]
        return torch.cat([torch.stack(rows).clamp(-1, 1), torch.zeros(len(idx), 1)], dim=-1)

    env.set_opponent_policy(lambda obs: act(env.opponent_idx))
    res = run_races(env, lambda obs: act(env.learner_idx))
    others = [s for s in range(4) if s not in chase]
    assert res.crashed[0, [0, partner]].all() and not res.crashed[0, others].any()
    assert res.crash_partner[0, 0] == partner and res.crash_partner[0, partner] == 0
    assert (res.crash_partner[0, others] == -1).all()
    assert (res.crash_time[0, [0, partner]] > 0).all() and (res.crash_time[0, others] == 0).all()
    kind = "teammate" if partner == 1 else "opponent"
    summary = summarize_races(res)
    assert summary["drone_contacts"] == {"teammate": 0, "opponent": 0, kind: 2}
    assert summary["crash_gates"] == {"0": 2}
    # flying at each other, each had the other ahead of it; drones that did not touch anyone record no bearing
    assert summary["contact_bearing"] == {"ahead": 2, "beside": 0, "behind": 0}
    assert (res.contact_bearing[0, others] == -1).all()
    # both closed in alike, so neither flew into the other alone
    assert summary["contact_fault"]["even"] == 2 and summary["contact_fault"]["mean_share"] == pytest.approx(0.5)
    assert (res.contact_fault[0, others] == -1).all()


def test_race_results_charge_a_contact_to_the_drone_that_flew_into_a_hovering_one(oval2):
    """Drone 0 flies at drone 1, which hovers where it started: drone 0's share of the contact is 1 (``own``),
    drone 1's is 0 (``other``); the summary of either team counts its own drone's side only."""
    env = make_env(oval2, worlds=1, drones=2, learners=(0,), training=False)
    env.set_opponent_policy(lambda obs: torch.zeros(1, 4))
    res = run_races(env, lambda obs: torch.cat([((env.pos[1] - env.pos[0]) / env.cfg.action.pos_scale).clamp(-1, 1),
                                                torch.zeros(1)])[None])
    assert res.crashed[0].all() and res.contact_fault[0].tolist() == pytest.approx([1.0, 0.0], abs=0.05)
    # the hovering drone drifts a hair (float32 hover thrust): the shares are 1 and 0 to well within 1e-3
    own, other = (summarize_races(res, [slot])["contact_fault"] for slot in (0, 1))
    assert own == pytest.approx({"own": 1, "even": 0, "other": 0, "mean_share": 1.0}, abs=1e-3)
    assert other == pytest.approx({"own": 0, "even": 0, "other": 1, "mean_share": 0.0}, abs=1e-3)


def test_race_results_count_a_pass_of_a_hovering_drone_for_both_sides(oval2):
    """Drone 0 starts 1.4 m before gate 0, behind drone 1, which hovers 0.4 m off the line 1 m before the gate; drone
    0 flies through the gate and on: it passes drone 1 once and is never passed, drone 1 the other way round."""
    env = make_env(oval2, worlds=1, drones=2, learners=(0,), training=False)
    env.set_opponent_policy(lambda obs: torch.zeros(1, 4))
    reset = env.reset

    def reset_and_place():
        reset()
        place(env, [[-1.4, -1.0, 1.0], [-0.9, -0.6, 1.0]])
        return env.current_observations()

    env.reset = reset_and_place
    res = run_races(env, waypoint_policy(env))
    assert not res.crashed[0].any() and res.gates_passed[0, 0] > 1
    assert res.passes[0].tolist() == [[1, 0], [0, 1]]
    summary = summarize_races(res, [0])
    assert summary["passes"] == pytest.approx({"made": 1, "suffered": 0, "made_per_race": 1.0,
                                                "suffered_per_race": 0.0})


def test_contact_bearing_splits_ahead_beside_and_behind_at_45_degrees():
    """Another drone within 45° of the direction of travel is ahead, within 45° of the opposite behind, else beside;
    next to a drone that stands still it is beside."""
    vel = torch.tensor([[2.0, 0.0, 0.0]] * 5 + [[0.0, 0.0, 0.0]])
    rel = torch.tensor([[0.1, 0.05, 0.0], [0.1, 0.0, -0.11], [0.0, 0.1, 0.0], [-0.1, 0.0, 0.09], [-0.1, -0.2, 0.0],
                        [0.1, 0.0, 0.0]])
    assert contact_bearing(rel, vel).tolist() == [0, 1, 1, 2, 1, 1]
    assert [BEARINGS[i] for i in contact_bearing(rel[:1], -vel[:1]).tolist()] == ["behind"]

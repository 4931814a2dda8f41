"""Training shield: its fade schedule, the target shift it adds in training only, and the intervention cost."""

from __future__ import annotations

import pytest
import torch
from pydantic import ValidationError

from spiral.config import AIRFRAMES, EnvCfg, ObsCfg, SimCfg, TrackSpec
from spiral.config.env import ShieldCfg
from spiral.env import RaceEnv, RaceSetting


@pytest.mark.parametrize(("progress", "scale"), [(0.0, 1.0), (0.2, 1.0), (0.35, 0.5), (0.5, 0.0), (0.9, 0.0)])
def test_shield_gain_falls_linearly_between_fade_start_and_fade_end(progress, scale):
    assert ShieldCfg(fade_start=0.2, fade_end=0.5).scale(progress) == pytest.approx(scale)


def test_a_shield_that_stops_before_it_starts_fading_is_refused():
    with pytest.raises(ValidationError, match="fade_end"):
        ShieldCfg(fade_start=0.6, fade_end=0.3)


def test_an_intervention_cost_without_a_shield_is_refused_naming_the_field():
    with pytest.raises(ValidationError, match=r"reward\.intervention"):
        EnvCfg(reward={"intervention": 0.5})


def closing_pair(track: TrackSpec, *, training: bool, weight: float = 0.5) -> RaceEnv:
    """Two drones 0.4 m apart along x and 0.1 m along y, closing at 2 m/s (the separation tests' hand-made case:
    a full-gain shift of 0.9 m each, sideways and in opposite directions)."""
    cfg = EnvCfg(obs=ObsCfg(history_len=1), episode={"track_start_prob": 0.0},
                 shield={"filter": {"distance": 0.25, "horizon_s": 0.4, "gain": 1.5}},
                 reward={"intervention": weight})
    env = RaceEnv(RaceSetting(track, AIRFRAMES["cf2x"], SimCfg()), cfg, world_count=1, drones_per_world=2,
                  learner_slots=(0, 1), seed=0, training=training)
    env.pos[:] = torch.tensor([[0.0, 0.0, 1.0], [0.4, 0.1, 1.0]])
    env.vel[:] = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    return env


@pytest.mark.parametrize("progress", [0.0, 0.25, 0.5])
def test_training_shield_shifts_targets_by_its_faded_gain_and_charges_the_full_shift(line2, progress):
    """Zero actions ask for the drones' own positions; the shield adds (1 − progress/0.5) · 0.9 m sideways, and each
    drone pays 0.5 · 0.9 for the step whatever the fade."""
    env = closing_pair(line2, training=True)
    env.set_training_progress(progress)
    pos = env.pos.clone()
    _, rewards, _, _ = env.step(torch.zeros(2, 4))
    scale = 1.0 - progress / 0.5
    torch.testing.assert_close(env.cmd[:, :3] - pos, scale * torch.tensor([[0.0, -0.9, 0.0], [0.0, 0.9, 0.0]]))
    torch.testing.assert_close(env.term_sums["intervention"], torch.full((2,), -0.5 * 0.9))
    assert float(rewards.max()) <= -0.45 + 0.1  # the cost outweighs any progress of one step


def test_evaluation_envs_fly_without_the_training_shield(line2):
    """A non-resetting env (evaluation, promotion, deployment) leaves the targets alone and charges nothing."""
    env = closing_pair(line2, training=False)
    pos = env.pos.clone()
    env.step(torch.zeros(2, 4))
    torch.testing.assert_close(env.cmd[:, :3], pos)
    assert not env.term_sums["intervention"].any()

"""The checkpoint file: checksummed round trips, refused damage, format-1 files, removed options read as today's
and settings saved before a field existed read with its old default."""

from __future__ import annotations

import pytest
import torch

from spiral.config.env import ObsCfg
from spiral.config.stage import StageSpec
from spiral.core.checkpoint import (
    FORMAT,
    LEGACY_DEFAULTS,
    CheckpointError,
    load_checkpoint,
    save_checkpoint,
    with_legacy_defaults,
)


def _layout(cfg: ObsCfg) -> dict:
    return {"obs_dim": 55, **cfg.model_dump()}


def test_a_saved_checkpoint_loads_with_its_state_and_metadata(tmp_path):
    layout = _layout(ObsCfg(history_len=1, teammates=True))
    save_checkpoint(tmp_path / "a.pt", {"w": torch.arange(3.0)}, {"obs_layout": layout, "stage": "solo"})
    data = load_checkpoint(tmp_path / "a.pt")
    torch.testing.assert_close(data["w"], torch.arange(3.0))
    assert data["spiral"]["format"] == FORMAT
    assert data["spiral"]["obs_layout"] == layout and data["spiral"]["stage"] == "solo"


def test_a_damaged_checkpoint_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "a.pt"
    save_checkpoint(path, {"w": torch.zeros(2)}, {"obs_layout": _layout(ObsCfg())})
    path.write_bytes(path.read_bytes()[:-7])
    with pytest.raises(CheckpointError, match=r"a\.pt: checksum mismatch"):
        load_checkpoint(path)


@pytest.mark.parametrize("cfg", [ObsCfg(history_len=1), ObsCfg(history_len=1, teammates=True, closest_approach=True)])
def test_a_format_1_layout_gains_the_options_it_left_out_when_they_were_off(tmp_path, cfg):
    """Format 1 dropped `teammates`, `priority` and `closest_approach` when off (and the horizon with the last): the
    loaded layout equals the one this version writes for the same options."""
    full = _layout(cfg)
    dropped = [k for k in ("teammates", "closest_approach") if not full[k]]
    dropped += ["approach_horizon_s"] if not full["closest_approach"] else []
    old = {k: v for k, v in full.items() if k not in dropped}
    save_checkpoint(tmp_path / "old.pt", {"w": torch.zeros(1)}, {"format": "spiral-checkpoint-1", "obs_layout": old})
    meta = load_checkpoint(tmp_path / "old.pt")["spiral"]
    assert meta["format"] == FORMAT and meta["obs_layout"] == full


def test_env_settings_of_removed_options_read_as_today_when_off_and_are_refused_when_on(tmp_path):
    """A checkpoint saved with the training shield and its reward term off and the policy's critic (as the shipped
    ones were) loads with env settings that today's EnvCfg accepts; one trained with the shield on, or with the race
    critic, is refused naming the option and the file."""
    from spiral.config.env import EnvCfg

    env = EnvCfg().model_dump()
    old = {**env, "shield": None, "critic": "policy", "reward": {**env["reward"], "intervention": 0.0}}
    save_checkpoint(tmp_path / "off.pt", {"w": torch.zeros(1)}, {"obs_layout": _layout(ObsCfg()), "env": old})
    assert EnvCfg.model_validate(load_checkpoint(tmp_path / "off.pt")["spiral"]["env"]) == EnvCfg()
    on = {**old, "shield": {"fade_end": 0.5}}
    save_checkpoint(tmp_path / "on.pt", {"w": torch.zeros(1)}, {"obs_layout": _layout(ObsCfg()), "env": on})
    with pytest.raises(CheckpointError, match=r"on\.pt: env\.shield: this checkpoint was trained with an option"):
        load_checkpoint(tmp_path / "on.pt")
    save_checkpoint(tmp_path / "race.pt", {"w": torch.zeros(1)}, {"obs_layout": _layout(ObsCfg()),
                                                                  "env": {**old, "critic": "race"}})
    with pytest.raises(CheckpointError, match=r"race\.pt: env\.critic: this checkpoint was trained with an option"):
        load_checkpoint(tmp_path / "race.pt")
    layout = {**_layout(ObsCfg()), "priority": False}  # an observation option removed since, stored off
    save_checkpoint(tmp_path / "obs.pt", {"w": torch.zeros(1)}, {"obs_layout": layout})
    assert load_checkpoint(tmp_path / "obs.pt")["spiral"]["obs_layout"] == _layout(ObsCfg())


def test_a_removed_option_nested_in_a_block_reads_as_today_whether_the_block_was_set_or_null(tmp_path):
    """``episode.passage_starts.pack`` stored off inside a passage-starts block leaves it; a null block loads
    untouched; a pack that was on is refused naming its whole path."""
    from spiral.config.env import EnvCfg

    env = EnvCfg().model_dump()
    block = {"share_start": 0.5, "share_end": 0.2, "capacity": 512, "pos_noise": 0.05, "vel_noise": 0.2}
    for name, stored, today in [("set", {**block, "pack": 0.0}, block), ("null", None, None)]:
        old = {**env, "episode": {**env["episode"], "passage_starts": stored}}
        save_checkpoint(tmp_path / f"{name}.pt", {"w": torch.zeros(1)}, {"obs_layout": _layout(ObsCfg()), "env": old})
        loaded = EnvCfg.model_validate(load_checkpoint(tmp_path / f"{name}.pt")["spiral"]["env"])
        assert loaded == EnvCfg.model_validate({**env, "episode": {**env["episode"], "passage_starts": today}})
    on = {**env, "episode": {**env["episode"], "passage_starts": {**block, "pack": 0.3}}}
    save_checkpoint(tmp_path / "on.pt", {"w": torch.zeros(1)}, {"obs_layout": _layout(ObsCfg()), "env": on})
    with pytest.raises(CheckpointError, match=r"env\.episode\.passage_starts\.pack: this checkpoint was trained"):
        load_checkpoint(tmp_path / "on.pt")


def test_settings_saved_before_a_field_existed_load_with_the_old_default_they_were_trained_with(tmp_path):
    """A checkpoint whose env, PPO and layout lack fields whose default has changed since (the closest-approach
    inputs, the proximity, closing and win weights, passage and track starts, the entropy bonus and bound loss)
    reads them at their old defaults, the paper's values; the fields it stored keep their values."""
    from spiral.config.env import EnvCfg
    from spiral.config.ppo import PPOCfg

    env = EnvCfg().model_dump()
    old_env = {"obs": {k: v for k, v in env["obs"].items() if k != "closest_approach"},
               "action": env["action"], "reward": {"progress": 1.0},
               "episode": {"track_start_speed": 1.0, "start_cut_prob": 0.5}}
    layout = {k: v for k, v in _layout(ObsCfg()).items() if k != "closest_approach"}
    meta = {"obs_layout": layout, "env": old_env, "ppo": {"learning_rate": 3e-4}}
    save_checkpoint(tmp_path / "old.pt", {"w": torch.zeros(1)}, meta)
    loaded = load_checkpoint(tmp_path / "old.pt")["spiral"]
    cfg, ppo = EnvCfg.model_validate(loaded["env"]), PPOCfg.model_validate(loaded["ppo"])
    assert not cfg.obs.closest_approach and not loaded["obs_layout"]["closest_approach"]
    assert cfg.obs.history_len == 1 and cfg.obs.teammates  # stored: kept
    assert (cfg.reward.proximity, cfg.reward.closing, cfg.reward.win) == pytest.approx((0.0, 0.0, 0.0))
    assert cfg.episode.passage_starts is None and cfg.episode.track_start_prob == pytest.approx(0.5)
    assert cfg.episode.start_cut_prob == pytest.approx(0.5)
    assert (ppo.entropy_coef, ppo.bound_loss_coef, ppo.learning_rate) == pytest.approx((0.005, 0.0, 3e-4))
    passages = {"episode": {"passage_starts": {"share_start": 0.4}}}
    assert with_legacy_defaults(passages, ("env",))["episode"]["passage_starts"]["share_end"] == pytest.approx(0.5)


def test_every_legacy_default_names_a_field_of_the_schema_whose_default_has_changed():
    """Each path of LEGACY_DEFAULTS is a field of a stage spec (a misspelt one would never be filled) whose default
    today differs from the old one."""
    today = StageSpec(name="s", scenario="1v1", iterations=1).model_dump()
    for path, old in LEGACY_DEFAULTS.items():
        block = today
        for key in path[:-1]:
            block = block[key]
        assert path[-1] in block, path
        assert block[path[-1]] != old, path

"""The checkpoint file: checksummed round trips, refused damage, format-1 files and removed options read as today's."""

from __future__ import annotations

import pytest
import torch

from spiral.config.env import ObsCfg
from spiral.core.checkpoint import FORMAT, CheckpointError, load_checkpoint, save_checkpoint


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
    """``episode.passage_starts.pack`` stored off inside a passage-starts block leaves it; a null block (the
    default) loads untouched; a pack that was on is refused naming its whole path."""
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

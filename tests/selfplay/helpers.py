"""Settings of the self-play stage tests: a small stage's common options and a promotion rule that always promotes."""

from __future__ import annotations

from spiral.config import AIRFRAMES

CF2X = AIRFRAMES["cf2x"]
COMMON = {"worlds": 8, "env": {"obs": {"history_len": 1, "gate_normals": True, "pid_integral": True}},
          "ppo": {"num_steps_per_env": 8, "save_interval": 1, "actor_hidden_dims": [16, 16],
                  "critic_hidden_dims": [16, 16]}}
SOLO = {**COMMON, "selection": {"interval": 2, "races": 2}}
"""A solo stage's options: COMMON with two evaluation races every second iteration (a multi-drone stage's come from
its promotion)."""
PERMISSIVE = {"promotion": {"interval": 1, "races": 4, "min_win_rate": 0.0, "max_success_drop": 1.0}}

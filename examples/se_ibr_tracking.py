"""How closely the PID follows a plan of the SE-IBR planner: a straight plan flown without replanning.

The plan of ``tests/baselines/test_tracking.py`` (from rest along +x, acceleration ramped to 6 m/s² and back within
0.72 s, 2.9 m/s) is flown through the env and its PID by ``SEIBRPlanner.follow``, with the default acceleration lead
(the attitude loop's lag) and without it. Prints the largest distance to the reference per setting.

Run: ``python examples/se_ibr_tracking.py``.
"""

from __future__ import annotations

import numpy as np
import torch

from spiral.baselines import SEIBRPlanner
from spiral.baselines.tracking import integrate_plan
from spiral.config import AIRFRAMES, EnvCfg, SimCfg, TrackSpec
from spiral.env import RaceEnv, RaceSetting

LINE2 = TrackSpec.model_validate({
    "kind": "track", "name": "line2",
    "gates": [{"position": [0.0, 0.0, 1.0], "rpy_deg": [0, 0, 0]}, {"position": [2.5, 0.0, 1.0], "rpy_deg": [0, 0, 0]}],
    "start": {"center": [-1.0, 0.0, 1.0], "size": [0.3, 0.3, 0.2]},
    "bounds": {"min": [-3.0, -3.0, 0.0], "max": [5.0, 3.0, 2.5]}, "time_limit_s": 6.0,
})


def max_tracking_error(**cfg: float) -> float:
    """Largest distance [m] between the drone and the reference while flying the straight plan."""
    env = RaceEnv(RaceSetting(LINE2, AIRFRAMES["cf2x"], SimCfg()), EnvCfg(), world_count=1, drones_per_world=1, seed=0,
                  training=False)
    env.reset()
    planner = SEIBRPlanner(env, **cfg)
    p0 = np.array([-2.0, 0.0, 1.0])
    env.pos[0], env.vel[0] = torch.tensor(p0, dtype=torch.float32), 0.0
    t = np.arange(planner.N + 1) * planner.cfg.dt
    acc = np.zeros((planner.N + 1, 3))
    acc[:, 0] = np.interp(t, [0.0, 0.24, 0.48, 0.72], [0.0, 6.0, 6.0, 0.0])
    pos, _ = integrate_plan(p0, np.zeros(3), acc, planner.cfg.dt)
    planner.plans[0, 0], planner.plan_acc[0, 0], planner.plan_v0[0, 0] = pos, acc, 0.0
    planner.has_plan[0, 0], planner.plan_time[0] = True, 0.0
    worst = 0.0
    for k in range(round(planner.N * planner.cfg.dt / env.dt)):
        ref = planner.reference(np.array([0]), np.array([k * env.dt]))[0][0]
        worst = max(worst, float(np.linalg.norm(env.pos[0].numpy() - ref)))
        env.step(planner.follow(torch.arange(1)))
    return worst


if __name__ == "__main__":
    print(f"acceleration lead = attitude lag (default): {max_tracking_error():.4f} m")
    print(f"no acceleration lead:                       {max_tracking_error(accel_lead=0.0):.4f} m")

"""Flight limits: closed forms from a hand-made airframe, and the shares the planner takes of them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spiral.baselines import SEIBRCfg, flight_limits
from spiral.baselines.limits import PID_THRUST_FLOOR
from spiral.baselines.se_ibr import plan_limits
from spiral.config import AIRFRAMES, EnvCfg, SimCfg
from spiral.config.airframe import AirframeCfg, PIDCfg
from spiral.config.env import ActionCfg
from spiral.env import RaceEnv, RaceSetting

G = 9.81


def airframe(*, twr: float, tilt_deg: float, max_accel: float = 100.0, drag=(0.25, 0.25, 0.5)) -> AirframeCfg:
    """A 0.5 kg quadrotor with the given thrust-to-weight, tilt limit, acceleration cap and drag [N·s/m]."""
    pid = PIDCfg(pos_p=(6.0, 6.0, 9.0), pos_d=(3.0, 3.0, 4.5), att_p=(300.0, 300.0, 100.0), att_d=(30.0, 30.0, 20.0),
                 max_tilt_deg=tilt_deg, max_accel=max_accel)
    return AirframeCfg(name="hand", mass=0.5, arm=0.1, kf=1e-8, km=1e-10, inertia=(1e-3, 1e-3, 2e-3),
                       thrust_to_weight=twr, radius=0.1, drag=drag, pid=pid)


def test_tilt_limited_airframe_gives_closed_form_acceleration_and_terminal_speed():
    """TWR 2, tilt 45°, drag/mass 0.5 per s: level g·tan 45° = g, terminal speed g/0.5, climb (2g − g)/1.0."""
    lim = flight_limits(airframe(twr=2.0, tilt_deg=45.0), ActionCfg(pos_scale=1.5), gravity=G)
    assert lim.thrust == pytest.approx(2.0 * G)
    assert lim.level_accel == pytest.approx(G)  # tilt, not thrust (g·√3), limits it
    assert lim.up_accel == pytest.approx(G)
    assert lim.down_accel == pytest.approx((1.0 - PID_THRUST_FLOOR) * G)
    assert lim.drag_per_mass == pytest.approx((0.5, 0.5, 1.0))
    assert lim.terminal_speed == pytest.approx(G / 0.5)  # 19.62 m/s
    assert lim.climb_speed == pytest.approx(G / 1.0)
    assert lim.action_speed == pytest.approx((3.0, 3.0, 3.0))  # K_p·reach/K_d = 6·1.5/3 and 9·1.5/4.5
    assert lim.attitude_lag == pytest.approx(0.1)  # att_d/att_p = 30/300


def test_thrust_limited_airframe_and_acceleration_cap():
    """TWR 1.5 at 60° gives g·√(1.5² − 1) level; a 20 m/s² cap on TWR 3 gives thrust 20; no drag, no terminal speed."""
    weak = flight_limits(airframe(twr=1.5, tilt_deg=60.0), ActionCfg(), gravity=G)
    assert weak.level_accel == pytest.approx(G * math.sqrt(1.5**2 - 1.0))  # 10.97 < g·tan 60° = 16.99
    capped = flight_limits(airframe(twr=3.0, tilt_deg=60.0, max_accel=20.0, drag=(0.0, 0.0, 0.0)), ActionCfg(),
                           gravity=G)
    assert capped.thrust == pytest.approx(20.0)
    assert capped.level_accel == pytest.approx(G * math.tan(math.radians(60.0)))
    assert math.isinf(capped.terminal_speed) and math.isinf(capped.climb_speed)
    absolute = flight_limits(airframe(twr=2.0, tilt_deg=45.0), ActionCfg(mode="absolute"), gravity=G)
    assert absolute.reach is None and absolute.action_speed is None


def test_planner_takes_its_shares_of_the_cf2x_limits(circuit6):
    """Plan with 0.85 of the thrust, 0.9 of the tilt, the whole reach and level accel / (3 × attitude lag) of jerk."""
    env = RaceEnv(RaceSetting(circuit6, AIRFRAMES["cf2x"], SimCfg()), EnvCfg(), world_count=1, drones_per_world=1,
                  seed=0, training=False)
    cfg = SEIBRCfg()
    lim = plan_limits(env, cfg)
    assert lim.thrust == pytest.approx(0.85 * 2.25 * G)
    assert lim.tan_tilt == pytest.approx(math.tan(math.radians(54.0)))
    assert lim.floor == pytest.approx(0.3 * G)
    np.testing.assert_allclose(lim.target_hi, 2.0)
    np.testing.assert_allclose(lim.target_lo, -2.0)
    level = min(G * math.tan(math.radians(60.0)), G * math.sqrt(2.25**2 - 1.0))
    assert lim.jerk == pytest.approx(level / (3.0 * 0.1))  # 56.6 m/s³
    np.testing.assert_allclose(lim.drag, np.array([0.01, 0.01, 0.02]) / 0.027)

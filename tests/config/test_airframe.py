"""Airframes: the built-in Crazyflie, field-by-field overrides, derived motor speeds."""

from __future__ import annotations

import pytest

from spiral.config import AIRFRAMES, AirframeSel, SpecError, resolve_airframe

G = 9.81


def test_cf2x_has_the_crazyflie_constants():
    """Match the Crazyflie 2.x numbers of the issue."""
    cf = AIRFRAMES["cf2x"]
    assert (cf.mass, cf.arm, cf.kf, cf.km) == pytest.approx((0.027, 0.0397, 3.16e-10, 7.94e-12), rel=1e-6, abs=0)
    assert cf.inertia == pytest.approx((1.4e-5, 1.4e-5, 2.17e-5), rel=1e-6, abs=0)
    assert cf.thrust_to_weight == pytest.approx(2.25)


def test_airframe_by_name_equals_the_built_in():
    """Resolve a bare name without overrides to the built-in airframe."""
    assert resolve_airframe("cf2x") == AIRFRAMES["cf2x"]


def test_override_replaces_only_the_named_fields():
    """Change arm and one PID gain, keeping every other field of cf2x."""
    cf = AIRFRAMES["cf2x"]
    custom = resolve_airframe(AirframeSel(overrides={"arm": 0.05, "pid": {"att_d": [30.0, 30.0, 10.0]}}))
    assert custom.arm == pytest.approx(0.05) and custom.pid.att_d == pytest.approx((30.0, 30.0, 10.0))
    assert custom.model_copy(update={"arm": cf.arm, "pid": cf.pid}) == cf


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"mas": 0.03}, "airframe.overrides.mas"),
        ({"pid": {"pos_pp": [1.0, 1.0, 1.0]}}, "airframe.overrides.pid.pos_pp"),
        ({"mass": -0.01}, "airframe.overrides.mass"),
        ({"thrust_to_weight": 0.9}, "airframe.overrides.thrust_to_weight"),
    ],
)
def test_bad_override_names_the_file_and_the_field(overrides, field):
    """Report a misspelt or invalid override as `<file>: airframe.overrides.<key>: ...`."""
    with pytest.raises(SpecError) as info:
        resolve_airframe(AirframeSel(overrides=overrides), source="p.yaml")
    assert info.value.problems[0].startswith(f"p.yaml: {field}: ")


def test_unknown_airframe_lists_the_known_ones():
    """Name the file, the field and the known airframes for an unknown name."""
    with pytest.raises(SpecError) as info:
        resolve_airframe(AirframeSel(name="cf3"), source="p.yaml")
    assert info.value.problems == ["p.yaml: airframe.name: unknown airframe 'cf3' (known: cf2x)"]


def test_max_rpm_follows_an_overridden_thrust_to_weight():
    """Solve 4·kf·max_rpm² = t2w·m·g for t2w = 3 while the hover speed stays put."""
    cf, strong = AIRFRAMES["cf2x"], resolve_airframe(AirframeSel(overrides={"thrust_to_weight": 3.0}))
    assert 4 * strong.kf * strong.max_rpm**2 == pytest.approx(3.0 * strong.mass * G)
    assert strong.max_rpm / strong.hover_rpm == pytest.approx(3.0**0.5)
    assert strong.hover_rpm == pytest.approx(cf.hover_rpm)

"""A bolted base's tilt: the link accelerometers' unmodelled-error floor stays however long
they are read, so the reported tilt sigma never falls below what it allows."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.tracking.fixed_base import floor_var_rad2, tilt_shortfall_var


def test_the_floors_combine_as_information_and_an_exact_sensor_says_none():
    # two 0.05 g floors: 0.05 / sqrt(2) rad (2.0°) about each horizontal axis
    assert np.isclose(np.degrees(np.sqrt(floor_var_rad2(np.array([0.05, 0.05])))), 2.026, atol=1e-3)
    assert np.isclose(floor_var_rad2(np.array([0.05, 0.1])), 1.0 / (400.0 + 100.0))
    assert floor_var_rad2(np.array([0.05, 0.0])) == 0.0  # a sensor the config says is exact
    assert floor_var_rad2(np.array([])) == 0.0


def test_the_reported_tilt_is_held_at_the_smaller_of_the_floor_and_the_start():
    f2 = floor_var_rad2(np.array([0.05, 0.05]))
    # the filter averaged the tilt down to 0.06°, from a start of 1°: held at 1° (the start knew
    # no better), never at 0.06°
    P, P0 = np.radians([0.06, 0.2]) ** 2, np.radians([1.0, 1.0]) ** 2
    got = np.sqrt(P + tilt_shortfall_var(f2, P, P0))
    assert np.degrees(got[0]) >= 1.0 - 1e-9 and np.degrees(got[1]) >= 1.0 - 1e-9
    # an installer's level at 0.1° is better than the floor allows: the level's sigma
    P, P0 = np.radians([0.06, 0.05]) ** 2, np.radians([0.1, 0.1]) ** 2
    got = np.sqrt(P + tilt_shortfall_var(f2, P, P0))
    assert np.all(np.degrees(got) >= 0.1 - 1e-9) and np.all(np.degrees(got) <= 0.1 + 1e-9)
    # a start wider than the floor: the floor's 2°
    P0 = np.radians([5.0, 5.0]) ** 2
    np.testing.assert_allclose(np.degrees(np.sqrt(P + tilt_shortfall_var(f2, P, P0))), 2.026, atol=1e-3)
    # already wider than the floor: nothing added
    assert np.all(tilt_shortfall_var(f2, np.radians([3.0, 3.0]) ** 2, P0) == 0.0)

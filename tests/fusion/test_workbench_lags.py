"""The moving workbench's instrument and its input test: an input the tracker itself measures
(the chair's acceleration, read off the IMU) is tested only at lags where it comes before the
innovation (a filter's innovation is orthogonal to the readings before it, not to those at or
after it), and the tracker it runs weighs the link accelerometers by their own noise."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.workbench.innovations import _first_lag, workbench_arm
from armfusion.fusion.workbench.whiteness import MAX_LAG, residual_analysis

N = 400
AXES = [("acc1", "acc1_x"), ("acc1", "acc1_y")]


def _inputs(rng):
    return {"chair accel x": rng.normal(size=N), "q1": np.cumsum(rng.normal(size=N))}


def test_a_measured_input_is_tested_only_where_it_comes_first():
    rng = np.random.default_rng(19)
    u = _inputs(rng)
    e = rng.normal(size=(N, 2))
    same = e.copy()
    same[:, 0] = 0.5 * u["chair accel x"] + np.sqrt(1 - 0.25) * e[:, 0]  # at the same instant
    first = _first_lag(0.5)
    # every lag: the same-instant correlation is flagged; from lag 1 on it is not evidence
    every = residual_analysis(same, AXES, u, 0.5).flagged()
    assert any(c.input == "chair accel x" and c.lag == 0 for c in every)
    a = residual_analysis(same, AXES, u, 0.5, min_lag=first)
    assert a.white, [(c.axis, c.input, round(c.r, 2), c.lag) for c in a.flagged()]
    # a residual that follows the input one block later is still caught
    later = e.copy()
    later[1:, 0] = 0.5 * u["chair accel x"][:-1] + np.sqrt(1 - 0.25) * e[1:, 0]
    f = residual_analysis(later, AXES, u, 0.5, min_lag=first).flagged()
    assert f and (f[0].input, f[0].lag) == ("chair accel x", 1), f[:2]


def test_the_tests_counted_are_those_made():
    rng = np.random.default_rng(20)
    u = _inputs(rng)
    e = rng.normal(size=(N, 2))
    every = residual_analysis(e, AXES, u, 0.5)
    some = residual_analysis(e, AXES, u, 0.5, min_lag=_first_lag(0.5))
    assert every.n_tests == 2 * 2 * (2 * MAX_LAG + 1)
    assert some.n_tests == 2 * (2 * MAX_LAG + 1) + 2 * MAX_LAG  # the chair's: lags 1 … 25
    assert some.band_flag < every.band_flag
    assert some.as_dict()["tests"] == some.n_tests


@pytest.mark.parametrize(("block_s", "lag"), [(0.5, 1), (0.25, 2), (1.0, 1)])
def test_the_first_lag_clears_the_input_s_averaging_window(block_s, lag):
    """The chair's acceleration is averaged over 0.5 s (centred): at lag L its window ends
    L·block - 0.25 s before the innovation's block starts half a block earlier."""
    first = _first_lag(block_s)
    assert first("chair accel y") == lag
    assert first("accel q3") == -MAX_LAG and first("temperature") == -MAX_LAG


def test_the_workbench_weighs_the_link_accelerometers_by_their_noise():
    arm = load_arm("wmra")
    assert arm.calibration.accel_floor_g("acc3") == pytest.approx(0.045)
    cal = replace(arm.calibration, accel_unmodelled_g_per_sensor={"acc2": 0.01})
    wb = workbench_arm(replace(arm, calibration=cal)).calibration
    assert [wb.accel_floor_g(s) for s in ("acc1", "acc2", "acc3", "acc4")] == [0.0] * 4
    assert wb.imu_accel_floor_g == pytest.approx(0.045)  # the IMU's: its bias state carries it

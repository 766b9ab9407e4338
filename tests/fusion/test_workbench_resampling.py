"""A stream linearly resampled from a lower rate is recognised from its noise, with the rate it
came from; a stream sampled at its own rate is not (seeded noise, a slow motion on top)."""

from __future__ import annotations

import numpy as np
import pytest
from armfusion.fusion.workbench.resampling import interpolation_pattern, resampling


def _motion(t):
    return np.column_stack([np.sin(0.7 * t), np.cos(0.4 * t), 0.3 * t])


@pytest.mark.parametrize(("source_hz", "rate_hz", "period"), [(100.0, 125.0, 5), (50.0, 125.0, 5),
                                                                (100.0, 200.0, 2)])
def test_linear_resampling_is_recognised_with_its_source_rate(source_hz, rate_hz, period):
    rng = np.random.default_rng(7)
    ts = np.arange(0.0, 30.0, 1.0 / source_hz)
    raw = _motion(ts) + rng.normal(0.0, 0.01, (len(ts), 3))
    t = np.arange(0.0, 29.9, 1.0 / rate_hz)
    out = np.column_stack([np.interp(t, ts, raw[:, c]) for c in range(3)])
    r = resampling("acc", t, out)
    assert r is not None and r.period == period
    assert r.source_hz == pytest.approx(source_hz, rel=1e-6)
    assert "linear interpolation from about" in r.words()


def test_a_stream_at_its_own_rate_is_not_flagged():
    for seed in range(5):
        rng = np.random.default_rng(seed)
        t = np.arange(0.0, 30.0, 1.0 / 125.0)
        assert resampling("acc", t, _motion(t) + rng.normal(0.0, 0.01, (len(t), 3))) is None


def test_the_pattern_of_100_to_125_hz():
    """A row on a sample keeps the noise's full variance; the second difference's variance runs
    2.07, 1.16, 0.30, 0.30, 1.16 of its mean over the five phases."""
    np.testing.assert_allclose(interpolation_pattern(5, 4, 0.0), [2.069, 1.164, 0.302, 0.302, 1.164],
                               atol=2e-3)

"""The fusion node's lag watch (``LagWatch``) judged on arrivals made up to the millisecond:
when a node on a starved machine is degraded, and when it is no longer."""

import numpy as np
from armfusion.fusion.service.lateness import LagWatch, Lateness


def _starved(watch: LagWatch, until_s: float = 8.0) -> list[tuple[float, bool, float]]:
    """A 100 Hz stream delivered 5 ms after its time, live from wall time 0; from 3 s to 6 s the
    node takes it in 60 ms late every other tenth of a second (a CPU share given in slices),
    on time otherwise; after 6 s on time, and nothing waits after each batch.
    Returns (wall time, degraded, lag) after each judgement."""
    out = []
    for t in np.arange(0.0, until_s, 0.01):
        late = 3.0 <= t < 6.0 and int(round(t * 10)) % 2 == 0
        arrived = t + 0.005
        now = arrived + (0.060 if late else 0.0)
        watch.taken("acc1", arrived, t)
        watch.judge(now)
        lag_s = watch.lag_s
        if not late and t >= 6.0:
            watch.nothing_waits(now)
        out.append((now, watch.degraded, lag_s))
    return out


def test_a_node_behind_in_slices_is_one_degraded_period_cleared_a_hold_after_it_was_last_behind():
    watch = LagWatch(Lateness())
    seen = _starved(watch)
    assert watch.periods == 1
    degraded_at = [now for now, d, _ in seen if d]
    assert 3.0 <= degraded_at[0] < 3.1
    # degraded through the slices, caught up a hold (1 s) after it was last behind
    last_behind = max(now for now, _, lag_s in seen if lag_s > 0.05)
    assert 5.9 < last_behind < 6.1
    assert 0.98 < degraded_at[-1] - last_behind < 1.0
    assert not seen[-1][1]


def test_without_the_hold_the_same_slices_flip_the_node_in_and_out():
    watch = LagWatch(Lateness(hold_s=0.0))
    _starved(watch)
    assert watch.periods >= 10

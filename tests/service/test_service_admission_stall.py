"""The sensors' clock after a stall (fusion/service/admission.py), without Zenoh: a starved
node or driver delivers genuine batches late and in a burst, some of them read before the
stall and stamped on arrival after it, one stream's backlog taken before another's. None
of them is refused; one sample stamped ahead is refused as before."""

from __future__ import annotations

import numpy as np
import pytest
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.admission import Admission
from armfusion.models.sensor_models import stream_models
from armfusion.sensors.samples import Stream

NAMES = ("acc1", "acc2", "imu_acc", "enc")
RATE_HZ = 100.0
EPOCH_S = 10.0
"""The sensors' time when the node's monotonic clock reads 0 (any origin will do)."""


@pytest.fixture(scope="module")
def arm():
    return load_arm("wmra")


@pytest.fixture(scope="module")
def models(arm):
    return stream_models(arm)


class Feed:
    """Genuine one-sample batches of every stream, each numbered in turn, checked by one
    :class:`Admission`; the verdicts refused are kept."""

    def __init__(self, arm, models):
        self.adm = Admission(arm)
        self.models = models
        self.seq = dict.fromkeys(NAMES, 0)
        self.refused: list[tuple[str, float, str]] = []

    def batch(self, name: str, t: float) -> pl.RawBatch:
        m = self.models[name]
        s = Stream(name, m.kind, np.array([t]), np.zeros((1, m.size), np.int64), m.channels)
        self.seq[name] += 1
        return pl.RawBatch("chair1", s, self.seq[name])

    def take(self, name: str, t: float, arrived_s: float, now_s: float | None = None) -> None:
        v = self.adm.check(self.batch(name, t), arrived_s if now_s is None else now_s, arrived_s)
        if not v.ok:
            self.refused.append((name, round(t, 3), v.message))

    def live(self, t0: float, t1: float) -> None:
        """Every stream from ``t0`` to ``t1``, each batch arriving as it is read."""
        for t in np.arange(t0, t1, 1.0 / RATE_HZ):
            for k in NAMES:
                self.take(k, t, t - EPOCH_S)


def _ticks(t0: float, t1: float) -> np.ndarray:
    return np.round(np.arange(t0, t1, 1.0 / RATE_HZ), 6)


@pytest.mark.parametrize("stall_s", [3.0, 40.0])
def test_a_starved_nodes_burst_taken_stream_by_stream_refuses_nothing(arm, models, stall_s):
    """The node's receive thread starved for ``stall_s``: every batch read meanwhile arrives
    at once, stamped on its late arrival; each stream's first backlog batch is taken, then
    acc1's whole backlog, then acc2's, and so on (the others' newest samples, stamped as
    they arrived, are then seconds older than acc1's)."""
    feed = Feed(arm, models)
    feed.live(10.0, 11.0)
    t_stall = 11.0
    burst_s = t_stall + stall_s - EPOCH_S  # the wall time the backlog arrives
    backlog = _ticks(t_stall, t_stall + stall_s)
    arrived = burst_s
    for k in NAMES:
        feed.take(k, backlog[0], arrived)
    for k in NAMES:
        for t in backlog[1:]:
            arrived += 1e-6
            feed.take(k, t, arrived, now_s=arrived + 0.5)  # (the node takes them later still)
    assert feed.refused == []
    feed.live(t_stall + stall_s, t_stall + stall_s + 0.5)  # and on it goes
    assert feed.refused == []


def test_batches_read_before_a_driver_stall_and_sent_after_it_refuse_nothing(arm, models):
    """The drivers stalled 3 s in the middle of a read: acc1 and acc2 were read before it,
    imu_acc and enc after; the batch goes out after it, so acc1's and acc2's newest samples
    arrive 3 s after they were read, next to imu_acc's and enc's read at once."""
    feed = Feed(arm, models)
    feed.live(10.0, 11.0)
    read_s, stall_s = 11.0, 3.0
    sent_s = read_s + stall_s - EPOCH_S
    for k in NAMES:
        feed.take(k, read_s if k in ("acc1", "acc2") else read_s + stall_s, sent_s)
    feed.live(read_s + stall_s + 0.01, read_s + stall_s + 1.0)
    assert feed.refused == []


@pytest.mark.parametrize("ahead_s", [1e6, 1.9, 0.5])
def test_one_sample_stamped_ahead_is_still_refused_after_a_stall(arm, models, ahead_s):
    """After the burst, and in the middle of it, a single sample stamped ahead of the
    sensors' time is refused, and the genuine ones go on being accepted."""
    feed = Feed(arm, models)
    feed.live(10.0, 11.0)
    backlog = _ticks(11.0, 14.0)
    arrived = 14.0 - EPOCH_S
    for k in NAMES:
        feed.take(k, backlog[0], arrived)
    for t in backlog[1:]:
        arrived += 1e-6
        feed.take("acc1", t, arrived)
    bogus = feed.batch("acc2", 14.0 + ahead_s)
    assert feed.adm.check(bogus, arrived, arrived).reason == "time_ahead"  # mid-burst
    for k in NAMES[1:]:
        for t in backlog[1:]:
            feed.take(k, t, arrived)
    assert feed.refused == []
    feed.live(14.0, 15.0)
    late = 15.0 - EPOCH_S
    bogus = feed.batch("imu_acc", 15.0 + ahead_s)
    assert feed.adm.check(bogus, late, late).reason == "time_ahead"  # after it
    stale = feed.batch("enc", 15.0 - 50.0)
    assert feed.adm.check(stale, late, late).reason == "time_behind"  # nor does one from the past pass
    feed.live(15.0, 15.5)
    assert feed.refused == []


def test_a_stream_that_paused_and_goes_on_live_is_judged_by_its_live_delay(arm, models):
    """A recording replayed as fast as it goes, then nothing for 5 s, then the rest live: the
    sensors' time stood still during the pause, so the clock follows the live samples (not
    the delay from before the pause), and one sample 1.9 s ahead of them is refused."""
    feed = Feed(arm, models)
    for t in _ticks(0.0, 3.0):  # 3 s of samples in 0.3 s of wall time
        for k in NAMES:
            feed.take(k, t, 0.1 * t)
    start_s = 0.3 + 5.0
    for t in _ticks(3.0, 3.5):
        for k in NAMES:
            feed.take(k, t, start_s + (t - 3.0))
    assert feed.refused == []
    now = start_s + 0.5
    assert feed.adm.check(feed.batch("acc1", 3.5 + 1.9), now, now).reason == "time_ahead"

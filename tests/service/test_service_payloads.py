"""Payloads on the wire: a round trip keeps every bit; a bad payload is counted and dropped."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from fusion.service import payloads as pl
from sensors.samples import Stream


def _batch(rng, n=5) -> pl.RawBatch:
    t = np.cumsum(rng.uniform(0.004, 0.006, n)) + 0.1
    counts = rng.integers(-4096, 4096, size=(n, 3))
    return pl.RawBatch("chair1", Stream("acc1", "accel", t, counts, ("acc1_x", "acc1_y", "acc1_z")), 7)


def test_raw_batch_round_trip_keeps_every_bit(rng):
    b = _batch(rng)
    got = pl.decode(pl.raw_key("chair1", "acc1"), pl.encode(b))
    assert isinstance(got, pl.RawBatch)
    assert got.seq == 7 and got.stream.channels == b.stream.channels
    np.testing.assert_array_equal(got.stream.t_s, b.stream.t_s)  # exact, not approximate
    np.testing.assert_array_equal(got.stream.values, b.stream.values)


def test_joint_state_heading_status_round_trip():
    js = pl.JointState("chair1", 1.5, ("q1", "q2"), (0.1, -0.2), (1e-3, 2e-3), ("ok", "gimbal_lock"))
    hd = pl.Heading("chair1", 1.5, 0.7, 0.01, True)
    st = pl.Status("chair1", "serve", "tracking", 1e9, "ok", (("published", 3),))
    for key, p in ((pl.joints_key("chair1"), js), (pl.heading_key("chair1"), hd),
                   (pl.status_key("chair1"), st)):
        assert pl.decode(key, pl.encode(p)) == p


def _good_raw(rng) -> dict:
    return _batch(rng).to_json()


BAD = {
    "not json": (b"\x80not json", "malformed"),
    "a list": (b"[1, 2]", "malformed"),
    "unknown version": (None, "unknown_version"),
    "missing counts": (None, "malformed"),
    "float counts": (None, "malformed"),
    "time going back": (None, "malformed"),
    "wrong sensor for key": (None, "malformed"),
    "oversized": (b" " * (pl.MAX_PAYLOAD_BYTES + 1), "oversized"),
}


def _bad_payload(case: str, rng) -> bytes:
    data, _ = BAD[case]
    if data is not None:
        return data
    d = _good_raw(rng)
    if case == "unknown version":
        d["v"] = 2
    elif case == "missing counts":
        del d["counts"]
    elif case == "float counts":
        d["counts"][0][0] = 1.5
    elif case == "time going back":
        d["t_s"][2] = d["t_s"][1] - 1.0
    elif case == "wrong sensor for key":
        d["sensor"] = "acc2"
    return json.dumps(d).encode()


@pytest.mark.parametrize("case", list(BAD))
def test_bad_payload_is_counted_and_dropped_with_one_log_line(case, rng, caplog):
    inbox = pl.Inbox("record")
    with caplog.at_level(logging.WARNING, logger="armfusion.service"):
        got = inbox.decode(pl.raw_key("chair1", "acc1"), _bad_payload(case, rng))
    assert got is None
    assert inbox.dropped == {BAD[case][1]: 1}
    assert inbox.received == 1
    assert len(caplog.records) == 1
    assert "record: dropped a payload on armfusion/chair1/raw/acc1" in caplog.records[0].getMessage()


def test_inbox_keeps_going_after_bad_payloads(rng):
    inbox = pl.Inbox("record")
    key = pl.raw_key("chair1", "acc1")
    for case in BAD:
        inbox.decode(key, _bad_payload(case, rng))
    assert inbox.decode(key, pl.encode(_batch(rng))) is not None
    assert sum(inbox.dropped.values()) == len(BAD)


def test_key_outside_armfusion_is_dropped():
    inbox = pl.Inbox("record")
    assert inbox.decode("other/chair1/raw/acc1", b"{}") is None
    assert inbox.dropped == {"bad_key": 1}


def test_names_in_keys_are_checked():
    with pytest.raises(ValueError, match=r"robot 'chair/\*': use 1 to 64 letters"):
        pl.raw_key("chair/*", "acc1")


def test_encode_refuses_an_oversized_batch():
    n = 40_000
    s = Stream("acc1", "accel", np.arange(1, n + 1) * 1e-3, np.full((n, 3), -123456789),
               ("acc1_x", "acc1_y", "acc1_z"))
    with pytest.raises(ValueError, match="publish smaller batches"):
        pl.encode(pl.RawBatch("chair1", s, 0))

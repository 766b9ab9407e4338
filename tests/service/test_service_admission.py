"""The fusion node's admission of raw batches (fusion/service/admission.py), without Zenoh:
each refusal with its reason and a message naming what and where; the sensors' clock, its
bootstrap and its recovery; encoder jumps and a board that really restarted; seq gaps that
a peer cannot inflate. And a hypothesis pass over the payload decoder and the admission."""

from __future__ import annotations

import json
import re
import time

import numpy as np
import pytest
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.admission import REASONS, Admission, AdmissionSettings
from armfusion.fusion.service.inbox import Inbox
from armfusion.models.sensor_models import stream_models
from armfusion.sensors.samples import Stream
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st


@pytest.fixture(scope="module")
def arm():
    return load_arm("wmra")


@pytest.fixture(scope="module")
def models(arm):
    return stream_models(arm)


def _raw(models, name: str, t_s, counts, seq: int = 0, channels=None, kind=None) -> pl.RawBatch:
    m = models[name]
    s = Stream(name, kind or m.kind, np.atleast_1d(np.asarray(t_s, float)), np.atleast_2d(counts),
               channels or m.channels)
    return pl.RawBatch("chair1", s, seq)


def _feed(adm, models, t0: float, t1: float, now_s: float, rate_hz: float = 100.0, seq0: int = 0,
          names=("acc1", "acc2", "imu_acc", "enc")):
    """Plausible batches of every named stream, one sample each, from t0 to t1 arriving in
    real time from wall time ``now_s`` on; all accepted."""
    for i, t in enumerate(np.arange(t0, t1, 1.0 / rate_hz)):
        for k in names:
            v = _raw(models, k, t, np.zeros(models[k].size, np.int64), seq=seq0 + i)
            verdict = adm.check(v, now_s + (t - t0))
            assert verdict.ok, (k, t, verdict)


def _live(adm, batch):
    """``adm``'s verdict on ``batch`` arriving as a live driver's would: on a wall clock that
    reads the batch's last sample time."""
    return adm.check(batch, float(batch.stream.t_s[-1]))


@pytest.mark.parametrize("change, reason, message", [
    (dict(name="acc9"), "unknown_sensor", r"sensor 'acc9' is not one of WMRA-II's \(acc1, acc2"),
    (dict(kind="gyro"), "wrong_kind", r"kind 'gyro', expected 'accel'"),
    (dict(channels=("acc1_x", "acc1_y")), "wrong_channels",
     r"2 channels \(acc1_x, acc1_y\), expected 3 \(acc1_x, acc1_y, acc1_z\)"),
    (dict(counts=[5000, 0, 0]), "out_of_range",
     r"acc1_x = 5000 at t = 1 s is beyond the device's range -512…511"),
])
def test_a_batch_the_arm_cannot_have_sent_is_refused_with_its_reason(arm, models, change, reason, message):
    adm = Admission(arm)
    name = change.get("name", "acc1")
    ch = change.get("channels") or (models["acc1"].channels if name == "acc1" else ("a_x", "a_y", "a_z"))
    counts = change.get("counts", np.zeros(len(ch), np.int64))
    s = Stream(name, change.get("kind", "accel"), np.array([1.0]), np.atleast_2d(counts), ch)
    v = adm.check(pl.RawBatch("chair1", s, 0), 0.0)
    assert v.reason == reason
    assert re.search(message, v.message), v.message
    assert adm.rejected == {reason: 1}


def test_encoder_counts_beyond_the_feeds_int32_and_jumps_are_refused(arm, models):
    adm = Admission(arm)
    assert _live(adm, _raw(models, "enc", 1.0, np.zeros(7, np.int64))).ok
    v = _live(adm, _raw(models, "enc", 1.01, np.full(7, 2**63 - 1)))
    assert v.reason == "out_of_range"
    assert "enc1 = 9223372036854775807 at t = 1.01 s is beyond the device's range" in v.message
    # 3 rad/s for 10 ms plus 0.5 deg of slack: 2.2 deg is fine, 174 deg is not
    cpr = arm.counts_per_rad
    ok = np.round(np.radians(2.2) * cpr).astype(np.int64)
    assert _live(adm, _raw(models, "enc", 1.01, ok)).ok
    jump = ok.copy()
    jump[3] += int(np.radians(174.0) * cpr[3])
    v = _live(adm, _raw(models, "enc", 1.02, jump))
    assert v.reason == "encoder_jump"
    assert v.message.startswith("enc4 moved 174° in 0.01 s at t = 1.02 s, more than the joint can turn")
    # the next real sample follows the last accepted one: fine
    assert _live(adm, _raw(models, "enc", 1.03, ok)).ok
    # a jump inside one batch is refused too
    two = np.vstack([ok, jump])
    assert _live(adm, _raw(models, "enc", [1.04, 1.05], two)).reason == "encoder_jump"


def test_an_encoder_board_that_restarted_is_taken_as_a_new_baseline_after_a_second(arm, models):
    adm = Admission(arm, AdmissionSettings(encoder_rebase_after_s=1.0))
    for t in np.arange(0.0, 0.5, 0.01):
        assert _live(adm, _raw(models, "enc", t, np.zeros(7, np.int64))).ok
    restarted = np.full(7, 1 << 30, np.int64)  # the board's counts start again elsewhere
    verdicts = [_live(adm, _raw(models, "enc", t, restarted)) for t in np.arange(0.5, 1.6, 0.01)]
    refused = [v for v in verdicts if not v.ok]
    assert all(v.reason == "encoder_jump" for v in refused)
    first_ok = next(i for i, v in enumerate(verdicts) if v.ok)
    assert verdicts[first_ok].rebased and adm.encoder_rebases == 1
    assert 0.99 <= 0.01 * first_ok <= 1.02  # after 1 s of agreeing refused samples
    assert all(v.ok for v in verdicts[first_ok:])


def test_bogus_counts_interleaved_with_real_ones_never_become_the_baseline(arm, models):
    adm = Admission(arm, AdmissionSettings(encoder_rebase_after_s=1.0))
    fake = np.full(7, 5_000_000, np.int64)
    for t in np.arange(0.0, 3.0, 0.01):
        assert _live(adm, _raw(models, "enc", t, np.zeros(7, np.int64))).ok
        assert _live(adm, _raw(models, "enc", t + 0.005, fake)).reason == "encoder_jump"
    assert adm.encoder_rebases == 0


def test_a_batch_far_from_the_sensors_clock_is_refused_and_does_not_move_it(arm, models):
    adm = Admission(arm)
    _feed(adm, models, 100.0, 101.0, now_s=0.0)
    v = adm.check(_raw(models, "acc1", 1e6, [0, 0, 256]), 1.0)
    assert v.reason == "time_ahead"
    assert v.message.startswith("t = 1e+06 s is 999899 s ahead of the other sensors' clock (3 streams)")
    v = adm.check(_raw(models, "acc1", 50.0, [0, 0, 256]), 1.0)
    assert v.reason == "time_behind"
    # the clock did not move: the real samples go on being accepted
    _feed(adm, models, 101.0, 101.5, now_s=1.0, seq0=100)
    assert adm.rejected == {"time_ahead": 1, "time_behind": 1}


def test_a_bogus_first_batch_holds_the_clock_only_until_its_vote_goes_stale(arm, models):
    adm = Admission(arm, AdmissionSettings(vote_fresh_s=2.0))
    assert adm.check(_raw(models, "acc1", 1e6, [0, 0, 256]), now_s=0.0).ok  # nothing to judge it by
    assert adm.check(_raw(models, "enc", 0.01, np.zeros(7, np.int64)), now_s=1.0).reason == "time_behind"
    # 2 s of wall time later acc1 no longer votes: the real streams set the clock, and acc1's
    # own real samples are accepted with a reset (the node forgets its bogus one)
    _feed(adm, models, 0.02, 0.1, now_s=2.5, names=("enc", "acc2", "imu_acc"))
    v = adm.check(_raw(models, "acc1", 0.1, [0, 0, 256]), now_s=2.5)
    assert v.ok and v.reset
    assert adm.check(_raw(models, "acc1", 1e6 + 1, [0, 0, 256]), now_s=2.6).reason == "time_ahead"


def test_samples_denser_than_any_sensor_samples_are_refused(arm, models):
    adm = Admission(arm, AdmissionSettings(max_rate_hz=1000.0))
    acc = np.array([0, 0, 256])
    assert _live(adm, _raw(models, "acc1", 1.00, acc)).ok
    # a plausible payload of 15,000 samples 0.1 ms apart would be seconds of tracker work
    t = 1.01 + 1e-4 * np.arange(15_000)
    v = _live(adm, _raw(models, "acc1", t, np.tile(acc, (len(t), 1))))
    assert v.reason == "too_dense"
    assert v.message == ("15000 samples in 1.5e+03 ms: denser than any sensor samples (at most "
                         "1000 Hz, bursts of 67)")
    # a driver that fell behind catches up: a few samples in quick succession are fine
    assert _live(adm, _raw(models, "acc1", 1.0002 + 1e-5 * np.arange(4), np.tile(acc, (4, 1)))).ok
    # and 1 kHz with jitter
    assert _live(adm, _raw(models, "acc1", [1.0107, 1.0115, 1.0121], np.tile(acc, (3, 1)))).ok
    # a steady stream of small batches faster than any sensor runs out of budget
    refused = 0
    for k in range(200):
        t0 = 1.02 + 1e-4 * 3 * k
        refused += _live(adm, _raw(models, "acc1", t0 + 1e-4 * np.arange(3),
                                   np.tile(acc, (3, 1)))).reason == "too_dense"
    assert refused > 100  # 10 kHz offered, 1 kHz kept: most batches refused


def test_a_driver_catching_up_after_a_stall_is_never_too_dense(arm, models):
    """What a driver hands on after a stall: its whole FIFO at once, stamped back from the
    read by the output period and squeezed 1 us apart where that meets the last stamp
    (sensors/adxl345.py), twice in one batch; or a second of samples at their own rate."""
    adm = Admission(arm)
    acc = np.array([0, 0, 256])
    for t in np.arange(0.0, 1.0, 0.005):
        assert _live(adm, _raw(models, "acc1", t, acc)).ok
    squeezed = 0.995 + 1e-6 * np.arange(1, 67)  # two FIFO reads of 33, squeezed onto the last stamp
    v = _live(adm, _raw(models, "acc1", squeezed, np.tile(acc, (66, 1))))
    assert v.ok, v.message
    after_stall = 1.5 + 0.005 * np.arange(200)  # a second of samples at 200 Hz after 0.5 s of nothing
    v = _live(adm, _raw(models, "enc", after_stall, np.zeros((200, 7), np.int64)))
    assert v.ok, v.message
    assert _live(adm, _raw(models, "acc1", after_stall, np.tile(acc, (200, 1)))).ok
    assert adm.rejected == {}


def test_seq_gaps_count_only_as_far_as_time_leaves_room(arm, models):
    adm = Admission(arm, AdmissionSettings(max_rate_hz=1000.0))
    acc = np.array([0, 0, 256])
    assert _live(adm, _raw(models, "acc1", 1.00, acc, seq=0)).ok
    # 5 batches lost in 20 ms: room for 20 at 1 kHz, counted
    v = _live(adm, _raw(models, "acc1", 1.02, acc, seq=6))
    assert v.missed == 5 and adm.missed_batches == 5
    # an invented seq 10 ms later: no room for a billion batches; and the real publisher's
    # next number follows its own (6), not the invented one: nothing counted, no new session
    v = _live(adm, _raw(models, "acc1", 1.03, acc, seq=10**9))
    assert v.ok and v.missed == 0 and not v.seq_reset
    v = _live(adm, _raw(models, "acc1", 1.04, acc, seq=7))
    assert v.missed == 0 and not v.seq_reset
    assert adm.missed_batches == 5 and adm.seq_resets == 0
    # a refused batch does not touch the numbers
    assert _live(adm, _raw(models, "acc1", 1.05, [9999, 0, 0], seq=10**12)).reason == "out_of_range"
    assert _live(adm, _raw(models, "acc1", 1.06, acc, seq=8)).missed == 0
    assert adm.missed_batches == 5


def test_one_batch_numbered_zero_among_real_ones_counts_nothing(arm, models):
    """A peer's single batch numbered 0 (what -1 was before the decoder refused signs) used
    to become the count's baseline, and the real publisher's next number then counted as
    152 missed batches."""
    adm = Admission(arm)
    acc = np.array([0, 0, 256])
    for k, t in enumerate(np.arange(0.0, 0.76, 0.005)):
        assert _live(adm, _raw(models, "acc1", t, acc, seq=k)).ok
    k += 1
    assert _live(adm, _raw(models, "acc1", 0.7601, acc, seq=0)).ok  # plausible, so accepted
    for j, t in enumerate(np.arange(0.765, 1.0, 0.005)):
        v = _live(adm, _raw(models, "acc1", t, acc, seq=k + j))
        assert v.ok and v.missed == 0 and not v.seq_reset
    assert adm.missed_batches == 0 and adm.seq_resets == 0


def test_a_publisher_that_restarts_its_numbers_is_a_new_session_once_they_go_on(arm, models):
    adm = Admission(arm)
    acc = np.array([0, 0, 256])
    for k, t in enumerate(np.arange(0.0, 0.5, 0.005)):
        assert _live(adm, _raw(models, "acc1", t, acc, seq=500 + k)).ok
    assert not _live(adm, _raw(models, "acc1", 0.5, acc, seq=0)).seq_reset  # one alone says nothing
    v = _live(adm, _raw(models, "acc1", 0.505, acc, seq=1))
    assert v.seq_reset and v.missed == 0
    assert _live(adm, _raw(models, "acc1", 0.52, acc, seq=4)).missed == 2  # gaps count from it
    assert adm.seq_resets == 1 and adm.missed_batches == 2


@pytest.mark.parametrize("top", [1 << 32, 1 << 63, 1 << 64])
def test_a_batch_counter_that_wraps_goes_on(arm, models, top):
    adm = Admission(arm)
    acc = np.array([0, 0, 256])
    assert _live(adm, _raw(models, "acc1", 1.000, acc, seq=top - 2)).ok
    assert _live(adm, _raw(models, "acc1", 1.005, acc, seq=top - 1)).ok
    v = _live(adm, _raw(models, "acc1", 1.010, acc, seq=0))
    assert v.ok and v.missed == 0 and not v.seq_reset
    v = _live(adm, _raw(models, "acc1", 1.020, acc, seq=2))  # one lost after the wrap
    assert v.missed == 1 and adm.missed_batches == 1 and adm.seq_resets == 0


@pytest.mark.parametrize("seq", [-1, -(2**70), 2**64])
def test_a_batch_number_beyond_an_unsigned_64_bit_counter_is_malformed(seq):
    d = _valid()
    d["seq"] = seq
    with pytest.raises(pl.PayloadError, match=r"field 'seq' = -?\d+ is not a batch number") as e:
        pl.decode(KEY, json.dumps(d).encode())
    assert e.value.reason == "malformed"


def test_one_sample_stamped_just_inside_the_old_window_is_refused_and_the_clock_holds(arm, models):
    """One accelerometer sample stamped 1.9 s ahead (inside the 2 s window the clock allowed)
    is refused; the real samples go on being accepted, none of them behind."""
    adm = Admission(arm)
    _feed(adm, models, 10.0, 11.0, now_s=0.0)
    v = adm.check(_raw(models, "acc1", 11.0 + 1.9, [0, 0, 256], seq=10**6), 1.0)
    assert v.reason == "time_ahead"
    assert re.match(r"t = 12\.9 s is 1\.9\d* s ahead of the other sensors' clock \(3 streams\)", v.message)
    clock = adm.clock(1.0)
    assert 10.98 <= clock <= 11.0  # (the streams' newest, carried 10 ms forward at most)
    _feed(adm, models, 11.0, 12.0, now_s=1.0, seq0=100)
    assert adm.rejected == {"time_ahead": 1}


def test_streams_silent_for_a_while_vote_on_with_wall_time(arm, models):
    """A stream whose driver ran while the others' stalled is not refused as ahead: their
    votes move on with the wall time since they arrived."""
    adm = Admission(arm)
    _feed(adm, models, 10.0, 11.0, now_s=0.0)
    v = adm.check(_raw(models, "enc", 11.8, np.zeros(7, np.int64), seq=1000), 1.8)  # the others quiet 0.8 s
    assert v.ok, v.message
    # but the same stamp arriving at once (no wall time passed) is ahead
    adm2 = Admission(arm)
    _feed(adm2, models, 10.0, 11.0, now_s=0.0)
    assert adm2.check(_raw(models, "enc", 11.8, np.zeros(7, np.int64), seq=1000), 1.0).reason == "time_ahead"


def test_messages_never_repeat_more_than_a_few_dozen_characters_of_a_value(arm, models):
    adm = Admission(arm)
    long_name = "x" * 64
    s = Stream(long_name, "accel", np.array([1.0]), np.zeros((1, 3)), ("a", "b", "c"))
    v = adm.check(pl.RawBatch("chair1", s, 0), 0.0)
    assert v.reason == "unknown_sensor" and "x" * 41 not in v.message


# --- fuzzing: the decoder and the admission take anything and raise only PayloadError --------

KEY = pl.raw_key("chair1", "acc1")
def _json_containers(inner):
    return st.one_of(st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=10), inner, max_size=5))


_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True) | st.text(max_size=20),
    _json_containers, max_leaves=30)


def _valid() -> dict:
    s = Stream("acc1", "accel", np.array([1.0, 1.01]), np.array([[1, 2, 250], [1, 3, 251]]),
               ("acc1_x", "acc1_y", "acc1_z"))
    return pl.RawBatch("chair1", s, 3).to_json()


def _mutated(field: str, value) -> bytes:
    d = _valid()
    d[field] = value
    return json.dumps(d, allow_nan=True).encode()


FIELDS = ("v", "type", "robot", "sensor", "kind", "channels", "seq", "t_s", "values")


PAYLOAD_REASONS = ("malformed", "oversized", "unknown_version", "bad_key")


def _decode_and_admit(data: bytes, adm: Admission) -> str | None:
    """What the node does with ``data``: the reason it is refused (by the decoder or the
    admission), or None when it is accepted. Any other exception fails the test."""
    t0 = time.perf_counter()
    try:
        payload = pl.decode(KEY, data)
    except pl.PayloadError as e:
        outcome = e.reason
    else:
        assert isinstance(payload, pl.RawBatch)
        outcome = adm.check(payload, 0.0).reason  # a verdict, never an exception
    assert time.perf_counter() - t0 < 1.0  # bounded work (a generous bound, not a benchmark)
    return outcome


@pytest.fixture(scope="module")
def fuzz_admission(arm):
    return Admission(arm)


@settings(derandomize=True, max_examples=300, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=200))
def test_fuzz_random_bytes_are_refused_with_a_reason(data, fuzz_admission):
    assert _decode_and_admit(data, fuzz_admission) in PAYLOAD_REASONS


@settings(derandomize=True, max_examples=400, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(field=st.sampled_from(FIELDS), value=_json)
def test_fuzz_one_field_of_a_valid_batch_replaced_by_any_json(field, value, fuzz_admission):
    assert _decode_and_admit(_mutated(field, value), fuzz_admission) in (*PAYLOAD_REASONS, *REASONS, None)


@settings(derandomize=True, max_examples=200, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(counts=st.lists(st.lists(st.integers(min_value=-(2**70), max_value=2**70), min_size=3, max_size=3),
                       min_size=1, max_size=4),
       t=st.lists(st.floats(allow_nan=False, allow_infinity=False, min_value=-1e300, max_value=1e300),
                  min_size=1, max_size=4))
def test_fuzz_counts_and_times_of_any_size(counts, t, fuzz_admission):
    d = _valid()
    n = min(len(counts), len(t))
    d["values"], d["t_s"] = counts[:n], sorted(set(t))[:n]
    d["values"] = d["values"][:len(d["t_s"])]
    outcome = _decode_and_admit(json.dumps(d).encode(), fuzz_admission)
    assert outcome in (*PAYLOAD_REASONS, *REASONS, None)
    if any(abs(c) >= 2**63 for row in d["values"] for c in row):
        assert outcome is not None  # counts no device gives are never accepted


def test_a_deeply_nested_payload_is_malformed_not_a_crash():
    data = b'{"v": 2, "type": "raw", "values": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    with pytest.raises(pl.PayloadError, match="not JSON") as e:
        pl.decode(KEY, data)
    assert e.value.reason == "malformed"


class _Sample:
    """What BoundedReceiver reads of a zenoh.Sample: its key expression and payload bytes."""

    class _Payload:
        def __init__(self, data: bytes):
            self._data = data

        def to_bytes(self) -> bytes:
            return self._data

    def __init__(self, key: str, data: bytes):
        self.key_expr, self.payload = key, self._Payload(data)


def test_a_flood_of_large_payloads_is_bounded_in_bytes_not_only_in_messages():
    from armfusion.fusion.service.node import BoundedReceiver

    mib = b" " * (1 << 20)
    rx = BoundedReceiver(maxsize=1000, block_s=0.05, max_bytes=3 << 20)
    for _ in range(5):
        rx(_Sample(KEY, mib))
    assert rx.overflowed == 2 and rx.queued_bytes == 3 << 20
    assert rx.get(0.1) is not None and rx.queued_bytes == 2 << 20
    rx(_Sample(KEY, mib))  # room again
    assert rx.overflowed == 2
    assert sum(1 for _ in iter(rx.get_nowait, None)) == 3 and rx.queued_bytes == 0


def test_a_flood_of_bad_payloads_is_counted_in_full_but_logged_once_a_second(caplog, arm, models):
    import logging

    inbox, adm = Inbox("serve"), Admission(arm)
    with caplog.at_level(logging.WARNING, logger="armfusion.service"):
        for i in range(1000):
            inbox.decode(KEY, b"\x80garbage")
            adm.check(_raw(models, "acc1", 1.0 + i * 1e-3, [5000, 0, 0]), 0.0)
    assert inbox.dropped == {"malformed": 1000} and adm.rejected == {"out_of_range": 1000}
    lines = [r.getMessage() for r in caplog.records]
    assert 2 <= len(lines) <= 10, lines  # the first of each reason, then one a second at most
    assert lines[0].startswith("serve: dropped a payload on armfusion/chair1/raw/acc1 (malformed)")
    assert any(m.startswith("serve: refused a batch of 'acc1' (out_of_range): acc1_x = 5000") for m in lines)


def test_values_in_g_are_held_to_the_range_the_description_declares():
    """The real rig's shaft IMU delivers g (range ±16 g in its config): a batch within it is
    admitted as it is, one reading beyond it refused naming the value as it came."""
    rig = load_arm("imu_rig_roll")
    adm = Admission(rig)
    ch = ("shaft_x", "shaft_y", "shaft_z")
    t = 10.0 + np.arange(3) * 0.01
    ok = np.array([[0.02, -0.98, 0.11], [0.03, -0.97, 0.12], [0.01, -0.99, 0.1]])
    verdict = adm.check(pl.RawBatch("rig", Stream("shaft", "accel", t, ok, ch), 0), 0.0)
    assert verdict.ok, verdict
    bad = ok.copy()
    bad[1, 2] = 16.5
    verdict = adm.check(pl.RawBatch("rig", Stream("shaft", "accel", t + 0.03, bad, ch), 1), 0.0)
    assert verdict.reason == "out_of_range" and "shaft_z = 16.5 at t = 10.04 s is beyond" in verdict.message

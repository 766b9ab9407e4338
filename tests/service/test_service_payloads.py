"""Payloads on the wire: a round trip keeps every bit; a bad payload is counted and dropped."""

from __future__ import annotations

import json
import logging
from dataclasses import replace

import numpy as np
import pytest
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service import raw_payload
from armfusion.fusion.service.inbox import Inbox
from armfusion.fusion.startup.combinations import Combination
from armfusion.fusion.tracking.estimate import Estimate
from armfusion.sensors.samples import Stream


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
    js = pl.JointState("chair1", 1.5, ("q1", "q2"), (0.1, -0.2), (1e-3, 2e-3), ("ok", "gimbal_lock"),
                       (("acc1", "ok"),), (88.5, 2.5))
    hd = pl.Heading("chair1", 1.5, 0.7, 0.01, 0.02, 1e-3, -0.03, 2e-3, (1e-4, -2e-4, 3e-5), True, False,
                    "disturbed", True)
    st = pl.Status("chair1", "serve", "tracking", 1e9, "ok", (("published", 3),))
    for key, p in ((pl.joints_key("chair1"), js), (pl.heading_key("chair1"), hd),
                   (pl.status_key("chair1"), st)):
        assert pl.decode(key, pl.encode(p)) == p


def _estimate() -> Estimate:
    return Estimate(t_s=2.25, q_rad=np.array([0.5, -1.25]), sigma_rad=np.array([1e-3, 2e-2]),
                    flags=("ok", "gimbal_lock"), roll_rad=0.01, pitch_rad=-0.02, yaw_rad=2.5,
                    attitude_sigma_rad=np.array([1e-3, 2e-3, 3e-2]),
                    gyro_bias_rad_s=np.array([1e-4, 0, -2e-4]), axis_to_vertical_deg=np.array([89.0, 1.5]),
                    sensors=(("acc1", "ok"), ("imu_mag", "rejecting")),
                    magnetic_disturbance=True, magnetic_recovery=False, joint_names=("j1", "j2"),
                    heading_status="compass_fused", true_north=True,
                    combinations=(Combination("j1 + j2", (("j1", 1.0), ("j2", 1.0)), -0.75, 4e-3),))


def test_an_estimate_has_one_wire_form_in_json_zenoh_and_mcap(tmp_path):
    """`track --json`, the Zenoh payloads and the recorder's MCAP messages carry the same
    fields with the same values: one record of the joints and one of the heading."""
    from armfusion.fusion.service.record import Recorder
    from armfusion.sensors.recording_mcap import McapRecorder
    from mcap.reader import make_reader

    est = _estimate()
    js, hd = pl.JointState.of("chair1", est), pl.Heading.of("chair1", est)
    assert est.as_dict() == {**js.record(), **hd.record()}
    assert est.as_dict()["heading_rad"] == 2.5 and est.as_dict()["heading_sigma_rad"] == 3e-2
    assert est.as_dict()["roll_sigma_rad"] == 1e-3 and est.as_dict()["axis_to_vertical_deg"] == [89.0, 1.5]
    envelope = {"v", "type", "robot"}
    for key, p, version in ((pl.joints_key("chair1"), js, 1), (pl.heading_key("chair1"), hd, 3)):
        wire = json.loads(pl.encode(p))
        assert wire["v"] == version and {k: v for k, v in wire.items() if k not in envelope} == p.record()
        assert pl.decode(key, pl.encode(p)) == p

    class Msg:  # what the recorder's receiver hands it
        def __init__(self, key, payload):
            self.key, self.data = key, pl.encode(payload)

    rec = Recorder(None, tmp_path / "r.mcap", "chair1")  # only its writing of what it received: no session
    with McapRecorder(tmp_path / "r.mcap") as mcap:
        rec._write(mcap, Msg(pl.joints_key("chair1"), js))
        rec._write(mcap, Msg(pl.heading_key("chair1"), hd))
    with open(tmp_path / "r.mcap", "rb") as fh:
        reader = make_reader(fh)
        got = {ch.topic: json.loads(m.data) for _, ch, m in reader.iter_messages()}
        schemas = {s.name: json.loads(s.data) for s in reader.get_summary().schemas.values()}
    assert got == {"estimates/joints": est.joints_record(), "estimates/heading": est.heading_record()}
    # the channels' JSON schemas name exactly the records' fields, for other MCAP readers
    joints_schema, heading_schema = schemas["armfusion.JointState"], schemas["armfusion.Heading"]
    assert set(joints_schema["properties"]) == set(est.joints_record())
    optional = {"axis_to_vertical_deg", "combinations"}
    assert set(joints_schema["required"]) == set(est.joints_record()) - optional
    assert est.as_dict()["combinations"] == [{"name": "j1 + j2", "coefficients": {"j1": 1.0, "j2": 1.0},
                                              "angle_rad": -0.75, "sigma_rad": 4e-3}]
    assert set(heading_schema["properties"]) == set(heading_schema["required"]) == set(est.heading_record())
    import jsonschema

    jsonschema.validate(got["estimates/joints"], joints_schema)
    jsonschema.validate(got["estimates/heading"], heading_schema)
    with pytest.raises(jsonschema.ValidationError, match="'heading_sigma_rad' is a required property"):
        jsonschema.validate({k: v for k, v in est.heading_record().items() if k != "heading_sigma_rad"},
                            heading_schema)


def test_a_version_1_heading_is_refused_naming_the_version():
    old = {"v": 1, "type": "heading", "robot": "chair1", "t_s": 1.0, "heading_rad": 0.5, "sigma_rad": 0.01,
           "magnetic_disturbance": False}
    with pytest.raises(pl.PayloadError, match="heading payload version 1; this node reads version 3"):
        pl.decode(pl.heading_key("chair1"), json.dumps(old).encode())


@pytest.mark.parametrize("heading_deg, enu_deg", [(0.0, 90.0), (90.0, 180.0), (-90.0, 0.0), (180.0, -90.0),
                                                  (-179.0, -89.0), (100.0, -170.0)])
def test_the_heading_feed_gives_enu_yaw_for_a_localisation_stack(heading_deg, enu_deg):
    """REP 103: yaw counter-clockwise from east. A chair facing north (heading 0) is at ENU
    yaw +90°, facing west (+90°, counter-clockwise from north) at 180°, facing east at 0."""
    est = replace(_estimate(), yaw_rad=float(np.radians(heading_deg)))
    rec = est.heading_record()
    assert rec["yaw_enu_rad"] == pytest.approx(np.radians(enu_deg))
    assert -np.pi < rec["yaw_enu_rad"] <= np.pi
    assert rec["yaw_enu_variance_rad2"] == pytest.approx(3e-2**2)
    assert rec["north"] == "true" and rec["heading_status"] == "compass_fused"


def test_a_heading_with_an_unknown_status_is_refused_naming_it():
    doc = json.loads(pl.encode(pl.Heading.of("chair1", _estimate())))
    doc["heading_status"] = "fine"
    with pytest.raises(pl.PayloadError, match="heading_status 'fine': expected one of compass_fused"):
        pl.decode(pl.heading_key("chair1"), json.dumps(doc).encode())
    good = pl.Heading.of("chair1", _estimate()).to_json()
    del good["magnetic_recovery"]
    with pytest.raises(pl.PayloadError, match="missing field 'magnetic_recovery'"):
        pl.decode(pl.heading_key("chair1"), json.dumps(good).encode())


def _good_raw(rng) -> dict:
    return _batch(rng).to_json()


BAD = {
    "not json": (b"\x80not json", "malformed"),
    "a list": (b"[1, 2]", "malformed"),
    "unknown version": (None, "unknown_version"),
    "missing values": (None, "malformed"),
    "float counts in version 1": (None, "malformed"),
    "a bool among the values": (None, "malformed"),
    "a NaN among the values": (None, "malformed"),
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
        d["v"] = 3
    elif case == "missing values":
        del d["values"]
    elif case == "float counts in version 1":  # version 1 holds whole register counts only
        d["v"], d["counts"] = 1, d.pop("values")
        d["counts"][0][0] = 1.5
    elif case == "a bool among the values":
        d["values"][0][0] = True
    elif case == "a NaN among the values":
        d["values"][0][0] = float("nan")
    elif case == "time going back":
        d["t_s"][2] = d["t_s"][1] - 1.0
    elif case == "wrong sensor for key":
        d["sensor"] = "acc2"
    return json.dumps(d).encode()


@pytest.mark.parametrize("case", list(BAD))
def test_bad_payload_is_counted_and_dropped_with_one_log_line(case, rng, caplog):
    inbox = Inbox("record")
    with caplog.at_level(logging.WARNING, logger="armfusion.service"):
        got = inbox.decode(pl.raw_key("chair1", "acc1"), _bad_payload(case, rng))
    assert got is None
    assert inbox.dropped == {BAD[case][1]: 1}
    assert inbox.received == 1
    assert len(caplog.records) == 1
    assert "record: dropped a payload on armfusion/chair1/raw/acc1" in caplog.records[0].getMessage()


def test_inbox_keeps_going_after_bad_payloads(rng):
    inbox = Inbox("record")
    key = pl.raw_key("chair1", "acc1")
    for case in BAD:
        inbox.decode(key, _bad_payload(case, rng))
    assert inbox.decode(key, pl.encode(_batch(rng))) is not None
    assert sum(inbox.dropped.values()) == len(BAD)


def test_key_outside_armfusion_is_dropped():
    inbox = Inbox("record")
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


def test_a_raw_batch_of_decimal_values_keeps_them_and_version_1_counts_still_read(rng):
    """A sensor whose description declares its values in g (an imported recording's) goes
    over the wire as they are, every bit kept; a version-1 batch of whole counts, from a
    publisher not yet updated, is read as before."""
    t = np.array([0.5, 0.51, 0.52])
    values = np.array([[0.01, -0.98, 0.13], [0.02, -0.97, 0.12], [1.0, 0.0, -0.25]])
    batch = pl.RawBatch("rig", Stream("shaft", "accel", t, values, ("shaft_x", "shaft_y", "shaft_z")), 3)
    back = pl.decode(pl.raw_key("rig", "shaft"), pl.encode(batch))
    np.testing.assert_array_equal(back.stream.values, values)
    assert back.stream.values.dtype == np.float64
    d = _good_raw(rng)
    d["v"], d["counts"] = 1, d.pop("values")
    old = pl.decode(pl.raw_key("chair1", "acc1"), json.dumps(d).encode())
    np.testing.assert_array_equal(old.stream.values, np.array(d["counts"]))
    assert old.stream.values.dtype == np.int64


def test_the_joints_payload_carries_the_combinations_gravity_reads_and_refuses_bad_ones():
    """``combinations`` is an optional field of the version-1 joints payload: a payload
    without it (an older publisher) is read as before; one with a non-finite sigma or a
    coefficient that is not a number is refused by name."""
    est = _estimate()
    js = pl.JointState.of("chair1", est)
    key = pl.joints_key("chair1")
    assert pl.decode(key, pl.encode(js)).combinations == js.combinations
    wire = json.loads(pl.encode(js))
    older = {k: v for k, v in wire.items() if k != "combinations"}
    assert pl.decode(key, json.dumps(older).encode()).combinations is None
    for bad, why in (({"sigma_rad": float("nan")}, "not finite|NaN"),
                     ({"coefficients": {"j1": "one"}}, "coefficients")):
        d = json.loads(json.dumps(wire))
        d["combinations"][0].update(bad)
        with pytest.raises(pl.PayloadError, match=why):
            pl.decode(key, json.dumps(d, allow_nan=True).encode())


_VARIANTS = {
    "a driver's batch": {},
    "a count of true": {"values": [[True, 0, 1], [2, 3, 4]]},
    "a decimal": {"values": [[0.5, 0, 1], [2, 3, 4]]},
    "a count of 2^63": {"values": [[2**63, 0, 1], [2, 3, 4]]},
    "a count of -2^63": {"values": [[-(2**63), 0, 1], [2, 3, 4]]},
    "a short row": {"values": [[0, 1], [2, 3, 4]]},
    "a row that is a string": {"values": ["abc", [2, 3, 4]]},
    "times not increasing": {"t_s": [1.0, 1.0]},
    "a time of 10^400": {"t_s": [1.0, 10**400]},
    "a time as text": {"t_s": [1.0, "2"]},
    "a channel that is a number": {"channels": ["acc1_x", 2, "acc1_z"]},
    "seq -1": {"seq": -1},
    "seq 2^64": {"seq": 2**64},
    "seq true": {"seq": True},
    "a sensor name with a slash": {"sensor": "acc/1"},
    "a kind of true": {"kind": True},
    "no values": {"values": [], "t_s": []},
    "version 1 counts": {"v": 1, "counts": [[0, 1, 2], [2, 3, 4]]},
}


@pytest.mark.parametrize("variant", list(_VARIANTS))
def test_a_raw_batch_decodes_the_same_by_the_quick_checks_and_field_by_field(variant, monkeypatch):
    """The node decodes a driver's plain batch with quick passes over its lists: whatever it
    receives, the outcome (the batch, or the refusal and its reason) is the one the checks
    field by field give."""
    doc = {"v": 2, "type": "raw", "robot": "chair1", "sensor": "acc1", "kind": "accel",
           "channels": ["acc1_x", "acc1_y", "acc1_z"], "seq": 3, "t_s": [1.0, 1.005],
           "values": [[0, 1, 2], [2, 3, 4]], **_VARIANTS[variant]}
    data = json.dumps(doc).encode()

    def outcome():
        try:
            b = pl.decode(pl.raw_key("chair1", "acc1"), data)
        except pl.PayloadError as e:
            return ("refused", e.reason, str(e))
        s = b.stream
        return ("batch", b.seq, s.name, s.kind, s.channels, s.t_s.tolist(), s.values.dtype.str,
                s.values.tolist())

    quick = outcome()
    monkeypatch.setattr(raw_payload, "_raw_plain", lambda d, robot: None)
    assert quick == outcome()
    if variant == "a driver's batch":
        assert quick[0] == "batch"

"""Recording MCAP: round trip, layout seen by other MCAP readers, recovery of cut files."""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from armfusion.sensors.recording import RecordingWarning, read_recording, write_recording
from armfusion.sensors.recording_mcap import McapRecorder, read_mcap, schema_for_kind, write_mcap
from armfusion.sensors.samples import (
    IMU_STREAMS,
    TRUTH_BASE_COLUMNS,
    Recording,
    RecordingError,
    Stream,
    accel_columns,
    encoder_columns,
    truth_joint_columns,
)
from mcap.reader import make_reader

REPO = Path(__file__).resolve().parents[2]


def _recording(seed: int = 0, duration_s: float = 2.0, t0_s: float = -1.5) -> Recording:
    """Every stream kind at its own rate, starting before t = 0."""
    rng = np.random.default_rng(seed)
    t = t0_s + np.arange(int(duration_s * 100)) * 0.01
    n = t.size
    s = [Stream("acc1", "accel", t, rng.integers(-512, 512, (n, 3)), accel_columns("acc1"))]
    s.append(Stream("acc2", "accel", t + 0.003, rng.integers(-512, 512, (n, 3)), accel_columns("acc2")))
    for name, (kind, cols) in IMU_STREAMS.items():
        step = {"imu_mag": 10, "imu_temp": 100}.get(name, 1)
        tt = t[::step]
        s.append(Stream(name, kind, tt, rng.integers(-32768, 32768, (tt.size, len(cols))), cols))
    s.append(Stream("enc", "encoder", t, rng.integers(-(10**9), 10**9, (n, 7)), encoder_columns(7)))
    s.append(Stream("true_q", "truth_joints", t, rng.uniform(-3, 3, (n, 7)), truth_joint_columns(7)))
    s.append(Stream("true_base", "truth_base", t, rng.normal(0, 0.1, (n, 3)), TRUTH_BASE_COLUMNS))
    return Recording({x.name: x for x in s}, meta={"arm_config": "wmra"})


def _assert_prefix_of(back: Recording, original: Recording) -> int:
    """Every recovered stream is the first samples of the original one; total count."""
    total = 0
    for name, b in back.streams.items():
        o = original.streams[name]
        assert (b.kind, b.channels) == (o.kind, o.channels)
        np.testing.assert_array_equal(b.t_s, o.t_s[: len(b)])
        np.testing.assert_array_equal(b.values, o.values[: len(b)])
        assert b.values.dtype == o.values.dtype
        total += len(b)
    return total


def _write_small_chunks(rec: Recording, path: Path) -> bytes:
    """The recording in many small chunks (4 kB uncompressed): many places to cut."""
    with McapRecorder(path, chunk_size_bytes=4096, t_offset_s=2.0) as r:
        for s in rec.streams.values():
            r.write_stream(s.between(-np.inf, -1.0))
        for s in rec.streams.values():
            r.write_stream(s.between(-1.0, np.inf))
    return path.read_bytes()


def _record_starts(data: bytes) -> list[int]:
    """Byte offsets where top-level records start (framing: opcode u8, length u64)."""
    starts, pos = [], 8
    while pos < len(data) - 8:
        starts.append(pos)
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        pos += 9 + length
    return starts


# ---------------------------------------------------------------------------- round trip


def test_round_trip_is_exact_and_keeps_the_metadata(tmp_path: Path) -> None:
    rec = _recording()
    write_mcap(rec, tmp_path / "r.mcap")
    back, report = read_mcap(tmp_path / "r.mcap")

    assert report.complete and report.bytes_unread == 0
    n = sum(len(s) for s in rec.streams.values())
    assert report.messages_read == n
    assert report.message == f"{tmp_path / 'r.mcap'}: complete: {n} messages up to t = 0.493 s"
    assert list(back.streams) == list(rec.streams)
    assert _assert_prefix_of(back, rec) == n  # all of it, bit for bit (floats too)
    assert back.meta["arm_config"] == "wmra"
    assert back.meta["armfusion_version"]
    assert back.meta["t_offset_ns"] == 2_000_000_000  # starts at -1.5 s: a 2 s offset


def test_other_mcap_readers_see_topics_schemas_and_metadata(tmp_path: Path) -> None:
    jsonschema = pytest.importorskip("jsonschema")
    rec = _recording(duration_s=0.5)
    write_mcap(rec, tmp_path / "r.mcap")
    with open(tmp_path / "r.mcap", "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert sorted(topics) == sorted(
            ["raw/acc1", "raw/acc2", "raw/imu_acc", "raw/imu_gyro", "raw/imu_mag", "raw/imu_temp"]
            + ["raw/enc", "truth/true_q", "truth/true_base"]
        )
        enc = topics["raw/enc"]
        assert enc.message_encoding == "json"
        assert enc.metadata == {
            "stream": "enc",
            "kind": "encoder",
            "channels": json.dumps(list(encoder_columns(7))),
        }
        schema = summary.schemas[enc.schema_id]
        assert (schema.name, schema.encoding) == ("armfusion.encoder", "jsonschema")
        assert json.loads(schema.data) == schema_for_kind("encoder")
        [meta] = [m for m in reader.iter_metadata() if m.name == "armfusion"]
        assert meta.metadata["arm_config"] == "wmra"
        assert meta.metadata["t_offset_ns"] == "2000000000"
        log_times = []
        validators = {
            s.id: jsonschema.Draft202012Validator(json.loads(s.data)) for s in summary.schemas.values()
        }
        for sch, _ch, msg in reader.iter_messages(log_time_order=False):
            sample = json.loads(msg.data)
            validators[sch.id].validate(sample)
            assert msg.log_time == msg.publish_time == round(sample["t_s"] * 1e9) + 2_000_000_000
            log_times.append(msg.log_time)
        assert log_times == sorted(log_times)  # streams merged in time order
        first = json.loads(next(reader.iter_messages())[2].data)
        assert first == {"t_s": -1.5, "values": rec.get("acc1").values[0].tolist()}


def test_a_message_that_breaks_its_schema_is_caught_by_the_schema() -> None:
    jsonschema = pytest.importorskip("jsonschema")
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"t_s": 0.0, "values": [1, 2]}, schema_for_kind("accel"))
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"t_s": 0.0, "values": [1, 2, "3.5"]}, schema_for_kind("gyro"))
    # raw values are numbers: counts, or decimals in the unit the sensor delivers
    jsonschema.validate({"t_s": 0.0, "values": [1, 2, 3.5]}, schema_for_kind("link_gyro"))
    assert schema_for_kind("accel")["properties"]["values"]["items"] == {"type": "number"}


def test_decimal_raw_values_and_a_link_gyro_round_trip_exactly_and_counts_stay_integers(
    tmp_path: Path,
) -> None:
    rng = np.random.default_rng(11)
    t = np.arange(200) * 0.01
    g = np.round(rng.normal(0.0, 1.0, (200, 3)), 2)  # g rounded to 0.01, as the rig stores them
    dps = rng.normal(0.0, 50.0, (200, 3))  # deg/s, every bit of the float
    enc = rng.integers(-(2**60), 2**60, (200, 1))
    rec = Recording({
        "shaft": Stream("shaft", "accel", t, g, accel_columns("shaft")),
        "shaft_gyro": Stream("shaft_gyro", "link_gyro", t, dps, ("shaft_gx", "shaft_gy", "shaft_gz")),
        "enc": Stream("enc", "encoder", t, enc, ("enc1",)),
    })
    write_mcap(rec, tmp_path / "r.mcap")
    back, report = read_mcap(tmp_path / "r.mcap")
    assert report.complete
    assert back.get("shaft").values.dtype == np.float64
    np.testing.assert_array_equal(back.get("shaft").values, g)
    np.testing.assert_array_equal(back.get("shaft_gyro").values, dps)
    assert back.get("shaft_gyro").kind == "link_gyro"
    assert back.get("enc").values.dtype == np.int64
    np.testing.assert_array_equal(back.get("enc").values, enc)
    from mcap.reader import make_reader

    with open(tmp_path / "r.mcap", "rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert topics == {"raw/shaft", "raw/shaft_gyro", "raw/enc"}


def test_a_file_whose_schema_says_integer_counts_reads_as_before(tmp_path: Path) -> None:
    # files written before raw values could be decimals carry "integer" in their schema
    from mcap.writer import Writer

    old = dict(schema_for_kind("accel"))
    old["properties"] = {**old["properties"], "values": {"type": "array", "items": {"type": "integer"}}}
    with open(tmp_path / "old.mcap", "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("armfusion.accel", "jsonschema", json.dumps(old).encode())
        cid = w.register_channel("raw/acc1", "json", sid, {"stream": "acc1", "kind": "accel",
                                                              "channels": '["acc1_x","acc1_y","acc1_z"]'})
        for i in range(3):
            w.add_message(cid, i, b'{"t_s":%d,"values":[%d,-2,250]}' % (i, i), i)
        w.finish()
    back, _ = read_mcap(tmp_path / "old.mcap")
    acc = back.get("acc1")
    assert acc.values.dtype == np.int64 and acc.values.tolist() == [[0, -2, 250], [1, -2, 250], [2, -2, 250]]


@pytest.mark.parametrize("version", ["1", "3"])
def test_a_file_of_a_format_version_this_armfusion_does_not_read_is_refused_naming_it(
        tmp_path: Path, version: str) -> None:
    """Version 1 (before raw values could be decimals) reads as before; a later version is
    refused with its number, not read as if its values meant what they did."""
    from mcap.writer import Writer

    with open(tmp_path / "v.mcap", "wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata("armfusion", {"format_version": version, "armfusion_version": "x", "arm_config": "",
                                     "t_offset_ns": "0"})
        schema = json.dumps(schema_for_kind("accel")).encode()
        sid = w.register_schema("armfusion.accel", "jsonschema", schema)
        cid = w.register_channel("raw/acc1", "json", sid, {"stream": "acc1", "kind": "accel",
                                                              "channels": '["acc1_x","acc1_y","acc1_z"]'})
        w.add_message(cid, 0, b'{"t_s":0,"values":[1,-2,250]}', 0)
        w.finish()
    if version == "1":
        back, _ = read_mcap(tmp_path / "v.mcap")
        assert back.get("acc1").values.tolist() == [[1, -2, 250]]
    else:
        with pytest.raises(RecordingError,
                           match=r"v\.mcap: armfusion MCAP format version '3'; this armfusion reads 1 or 2"):
            read_mcap(tmp_path / "v.mcap")


# ---------------------------------------------------------------------------- recorder


def test_recorder_writes_batches_and_json_topics(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    t = np.arange(50) * 0.02
    counts = rng.integers(-500, 500, (50, 3))
    with McapRecorder(tmp_path / "live.mcap", arm_config="crs_a465") as rec:
        for i in range(0, 50, 7):  # uneven batches, a single sample as N = 1 too
            rec.write_samples("acc3", "accel", accel_columns("acc3"), t[i : i + 7], counts[i : i + 7])
        rec.write_samples("enc", "encoder", ("enc1",), [1.0], [[2**60 + 1]])  # beyond float64
        rec.write_json("estimates/joints", "armfusion.JointEstimate", {"q_rad": [0.1, 0.2]}, t_s=0.5)
    back, report = read_mcap(tmp_path / "live.mcap")
    assert report.complete and report.messages_read == 52
    assert report.ignored_topics == ("estimates/joints",)
    np.testing.assert_array_equal(back.get("acc3").t_s, t)
    np.testing.assert_array_equal(back.get("acc3").values, counts)
    assert back.get("enc").values.tolist() == [[2**60 + 1]]
    assert back.meta["arm_config"] == "crs_a465"
    with open(tmp_path / "live.mcap", "rb") as f:
        [(_, ch, msg)] = make_reader(f).iter_messages(topics=["estimates/joints"])
    assert json.loads(msg.data) == {"q_rad": [0.1, 0.2]} and msg.log_time == 500_000_000


def test_recorder_refuses_what_it_cannot_store(tmp_path: Path) -> None:
    with McapRecorder(tmp_path / "x.mcap") as rec:
        rec.write_samples("acc1", "accel", accel_columns("acc1"), [1.0], [[1, 2, 3]])
        with pytest.raises(ValueError, match=r"t_s = 1.0 does not follow the last sample written"):
            rec.write_samples("acc1", "accel", accel_columns("acc1"), [1.0], [[1, 2, 3]])
        with pytest.raises(ValueError, match="was started as kind accel"):
            rec.write_samples("acc1", "gyro", ("a", "b", "c"), [2.0], [[1, 2, 3]])
        with pytest.raises(ValueError, match=r"t_s = -0.25 is before the recorder's time origin"):
            rec.write_samples("enc", "encoder", ("enc1",), [-0.25], [[1]])
        with pytest.raises(ValueError, match="reserved for sample streams"):
            rec.write_json("raw/acc1", "x", {}, t_s=1.0)
        with pytest.raises(ValueError, match=r"raw value nan at sample 0, channel 0 is not finite"):
            rec.write_samples("acc2", "accel", accel_columns("acc2"), [1.0], [[np.nan, 2, 3]])
    with pytest.raises(ValueError, match="the recorder is closed"):
        rec.write_samples("acc1", "accel", accel_columns("acc1"), [2.0], [[1, 2, 3]])


def test_a_recorder_that_never_closes_leaves_everything_flushed_readable(tmp_path: Path) -> None:
    """No close(), no footer: what a crash leaves. Flushing each write loses nothing."""
    rec_path = tmp_path / "open.mcap"
    rec = McapRecorder(rec_path, flush_interval_s=0.0)
    t = np.arange(30) * 0.01
    for i in range(30):
        rec.write_samples("acc1", "accel", accel_columns("acc1"), t[i : i + 1], [[i, -i, 2 * i]])
    back, report = read_mcap(rec_path)
    assert not report.complete
    assert report.messages_read == 30 and report.bytes_unread == 0
    assert "the file's summary is missing" in report.message
    np.testing.assert_array_equal(back.get("acc1").values[:, 0], np.arange(30))
    rec.close()
    assert read_mcap(rec_path)[1].complete


_CHILD = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from armfusion.sensors.recording_mcap import McapRecorder
    from armfusion.sensors.samples import accel_columns

    with McapRecorder(sys.argv[1], flush_interval_s=0.05) as rec:
        for i in range(100000):
            v = np.array([[i, i + 1, i + 2]])
            rec.write_samples("acc1", "accel", accel_columns("acc1"), [i * 0.01], v)
            print(i + 1, flush=True)
            time.sleep(0.005)
    """
)


def test_kill_9_while_recording_loses_at_most_the_last_chunk(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    child = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(path)], stdout=subprocess.PIPE, text=True, env=env
    )
    written = 0
    try:
        while written < 150:
            written = int(child.stdout.readline())
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait()
        child.stdout.close()
    back, report = read_mcap(path)
    assert not report.complete
    acc = back.get("acc1")
    # a flush every 0.05 s at ~100 samples/s: the last chunk holds a handful of samples
    assert len(acc) >= written - 60
    np.testing.assert_array_equal(acc.values[:, 0], np.arange(len(acc)))
    assert f"recovered {len(acc)} messages up to t = {acc.t_s[-1]:.3f} s" in report.message


# ---------------------------------------------------------------------------- cut files


def test_a_file_cut_anywhere_gives_back_every_complete_message(tmp_path: Path) -> None:
    rec = _recording(duration_s=1.0)
    data = _write_small_chunks(rec, tmp_path / "full.mcap")
    size = len(data)
    starts = _record_starts(data)
    assert len(starts) > 20
    rng = np.random.default_rng(11)
    cuts = {0, 3, 7, 8, 12, starts[2] + 5, size - 1, size - 4, size}
    cuts |= set(starts[:12])  # exactly at record boundaries: header, metadata, chunks
    cuts |= {s + 40 for s in starts[2:6]}  # inside the first chunks
    cuts |= set(rng.integers(0, size, 20).tolist())
    cuts = sorted(cuts)
    assert len(cuts) >= 40

    recovered_before = -1
    for cut in cuts:
        p = tmp_path / "cut.mcap"
        p.write_bytes(data[:cut])
        back, report = read_mcap(p)
        n = _assert_prefix_of(back, rec)
        assert n == report.messages_read
        assert n >= recovered_before, f"cut at {cut}: fewer messages than a shorter file"
        recovered_before = n
        assert report.bytes_total == cut
        assert 0 <= report.bytes_unread <= cut
        if cut < size:
            assert not report.complete
            assert f"file ends early at byte {cut}" in report.message
            lost = "could not be read" if report.bytes_unread else "the file's summary is missing"
            assert lost in report.message
    assert report.complete and recovered_before == sum(len(s) for s in rec.streams.values())


def test_a_cut_inside_a_chunk_says_that_chunk_is_lost(tmp_path: Path) -> None:
    rec = _recording(duration_s=1.0)
    data = _write_small_chunks(rec, tmp_path / "full.mcap")
    chunks = [s for s in _record_starts(data) if data[s] == 0x06]
    cut = chunks[3] + 100
    (tmp_path / "cut.mcap").write_bytes(data[:cut])
    back, report = read_mcap(tmp_path / "cut.mcap")
    (tmp_path / "upto.mcap").write_bytes(data[: chunks[3]])
    _, at_boundary = read_mcap(tmp_path / "upto.mcap")
    assert report.messages_read == at_boundary.messages_read > 0
    assert report.bytes_unread == 100
    assert report.message == (
        f"{tmp_path / 'cut.mcap'}: file ends early at byte {cut}, inside a chunk record that "
        f"starts at byte {chunks[3]}: recovered {report.messages_read} messages up to "
        f"t = {report.t_last_s:.3f} s; the last 100 bytes could not be read "
        "(the messages of that chunk are lost)"
    )


def test_a_damaged_chunk_ends_the_reading_there(tmp_path: Path) -> None:
    rec = _recording(duration_s=1.0)
    data = bytearray(_write_small_chunks(rec, tmp_path / "full.mcap"))
    chunks = [s for s in _record_starts(bytes(data)) if data[s] == 0x06]
    data[chunks[2] + 200] ^= 0xFF
    (tmp_path / "bad.mcap").write_bytes(bytes(data))
    back, report = read_mcap(tmp_path / "bad.mcap")
    (tmp_path / "upto.mcap").write_bytes(bytes(data[: chunks[2]]))
    assert report.messages_read == read_mcap(tmp_path / "upto.mcap")[1].messages_read
    _assert_prefix_of(back, rec)
    assert not report.complete
    assert f"a damaged chunk record at byte {chunks[2]}" in report.message


def test_a_file_that_is_not_mcap_is_named(tmp_path: Path) -> None:
    p = tmp_path / "notes.mcap"
    p.write_text("t,acc1_x,acc1_y,acc1_z\n0.0,1,2,3\n")
    with pytest.raises(ValueError, match=r"notes\.mcap: not an MCAP file"):
        read_mcap(p)


# ---------------------------------------------------------------------------- dispatcher


def test_read_and_write_recording_pick_the_format_by_suffix(tmp_path: Path) -> None:
    rec = _recording(duration_s=0.3)
    write_recording(rec, tmp_path / "r.MCAP")
    from_mcap = read_recording(tmp_path / "r.MCAP")
    assert from_mcap.meta["read_report"].complete
    write_recording(from_mcap, tmp_path / "r.csv")
    from_csv = read_recording(tmp_path / "r.csv")
    assert list(from_csv.streams) == list(rec.streams)
    np.testing.assert_array_equal(from_csv.get("enc").values, rec.get("enc").values)
    np.testing.assert_array_equal(from_csv.get("imu_mag").t_s, rec.get("imu_mag").t_s)


def test_read_recording_warns_when_an_mcap_file_ends_early(tmp_path: Path) -> None:
    data = _write_small_chunks(_recording(duration_s=1.0), tmp_path / "full.mcap")
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    with pytest.warns(RecordingWarning, match=r"cut\.mcap: file ends early at byte \d+, inside"):
        rec = read_recording(tmp_path / "cut.mcap")
    report = rec.meta["read_report"]
    assert not report.complete
    assert sum(len(s) for s in rec.streams.values()) == report.messages_read > 0


def test_an_unknown_suffix_is_named_with_the_accepted_ones(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"unknown recording suffix '\.bag'; expected \.csv or \.mcap"):
        read_recording(tmp_path / "run.bag")
    with pytest.raises(ValueError, match=r"run: unknown recording suffix '\(none\)'"):
        write_recording(_recording(duration_s=0.1), tmp_path / "run")


def _foreign_gyro_writer(f):
    """An MCAP writer of another program, started, with an ``imu_gyro`` channel of JSON
    messages as armfusion names them: ``(writer, schema id, channel id)``."""
    from mcap.writer import Writer

    w = Writer(f, use_chunking=False)
    w.start()
    sid = w.register_schema("armfusion.gyro", "jsonschema", b"{}")
    meta = {"stream": "imu_gyro", "kind": "gyro", "channels": '["imu_gx","imu_gy","imu_gz"]'}
    return w, sid, w.register_channel("raw/imu_gyro", "json", sid, meta)


def test_reads_a_file_from_another_mcap_writer(tmp_path: Path) -> None:
    """Same topics and channel metadata, but JSON spelled differently and no chunks."""

    with open(tmp_path / "other.mcap", "wb") as f:
        w, sid, cid = _foreign_gyro_writer(f)
        other = w.register_channel("/tf", "json", sid, {})
        for i in range(5):
            msg = {"values": [i, -i, 2**40 + i], "t_s": 0.1 * i}  # keys swapped, spaces
            w.add_message(cid, i, json.dumps(msg, indent=1).encode(), i)
            w.add_message(other, i, b"{}", i)
        w.finish()
    back, report = read_mcap(tmp_path / "other.mcap")
    assert report.complete and report.messages_read == 10
    assert report.ignored_topics == ("/tf",)
    gyro = back.get("imu_gyro")
    np.testing.assert_array_equal(gyro.t_s, 0.1 * np.arange(5))
    np.testing.assert_array_equal(gyro.values[:, 2], 2**40 + np.arange(5))
    assert back.meta == {"source": str(tmp_path / "other.mcap"),  # no armfusion metadata
                         "mcap_topics": {"imu_gyro": "raw/imu_gyro"}}


@pytest.mark.parametrize("values, why", [
    ("[1, 2, 100000000000000000000000]", "raw counts must be 64-bit integers"),
    ("[1, 2, " + "[" * 100_000 + "]" * 100_000 + "]", "RecursionError"),
    ('[1, 2, "x"]', "ValueError"),
])
def test_messages_that_do_not_fit_are_refused_naming_the_topic(
    tmp_path: Path, values: str, why: str
) -> None:

    from armfusion.sensors.samples import RecordingError

    with open(tmp_path / "bad.mcap", "wb") as f:
        w, _, cid = _foreign_gyro_writer(f)
        w.add_message(cid, 0, b'{"t_s": 0.0, "values": [1, 2, 3]}', 0)
        w.add_message(cid, 1, ('{"t_s": 0.1, "values": ' + values + "}").encode(), 1)
        w.finish()
    with pytest.raises(RecordingError, match=r"bad\.mcap: topic 'raw/imu_gyro': messages do not "
                                             r"fit the stream: ") as caught:
        read_mcap(tmp_path / "bad.mcap")
    assert why in str(caught.value) and len(str(caught.value)) < 300


def test_a_recording_longer_than_a_write_slice_is_written_whole_and_in_order(tmp_path, monkeypatch):
    """``write_mcap`` makes a slice of time's messages at a time (memory bounded by the slice,
    not the recording): every sample comes back, each stream in order, the file's messages in
    time order across the slices, samples at a slice's edge included once."""
    import armfusion.sensors.recording_mcap as rm

    monkeypatch.setattr(rm, "WRITE_SLICE_S", 1.0)
    t_fast = np.arange(0, 500) * 0.01  # 5 s at 100 Hz: 1.0, 2.0 … fall on slice edges
    t_slow = np.arange(0, 50) * 0.1
    rec = Recording({
        "acc1": Stream("acc1", "accel", t_fast, np.arange(1500).reshape(500, 3),
                       ("acc1_x", "acc1_y", "acc1_z")),
        "enc": Stream("enc", "encoder", t_slow, np.arange(50).reshape(50, 1) * 7, ("enc1",)),
    })
    write_mcap(rec, tmp_path / "r.mcap")
    back = read_recording(tmp_path / "r.mcap")
    for name in rec.streams:
        np.testing.assert_array_equal(back.get(name).t_s, rec.get(name).t_s)
        np.testing.assert_array_equal(back.get(name).values, rec.get(name).values)
    with open(tmp_path / "r.mcap", "rb") as f:
        times = [m.log_time for _s, _c, m in make_reader(f).iter_messages(log_time_order=False)]
    assert times == sorted(times) and len(times) == 550

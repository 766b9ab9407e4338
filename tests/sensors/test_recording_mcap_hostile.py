"""Recording MCAP against hostile and broken files: a time or a count no sensor can have said
is refused naming the topic and message, a sample topic the reader cannot take (an unknown
kind, no metadata) is named, not left out silently; fuzzing over damaged files checks that
the reader returns a recording every door's rules pass, or its own one-line error."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from armfusion.sensors.recording import RecordingWarning, read_recording, write_recording
from armfusion.sensors.sample_checks import feed_problems
from armfusion.sensors.samples import Recording, RecordingError, Stream
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.writer import Writer

CHANNELS = ["acc1_x", "acc1_y", "acc1_z"]


def _mcap(path: Path, messages: list[bytes], *, kind: str | None = "accel", topic: str = "raw/acc1") -> Path:
    """One channel of ``messages`` (``kind`` None: a channel without the stream's metadata)."""
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        meta = {} if kind is None else {"stream": "acc1", "kind": kind, "channels": json.dumps(CHANNELS)}
        cid = w.register_channel(topic, "json", sid, meta)
        for i, m in enumerate(messages):
            w.add_message(cid, i, m, i)
        w.finish()
    return path


def _good(n: int = 20) -> list[bytes]:
    return [b'{"t_s":%r,"values":[1,2,256]}' % (i * 0.01) for i in range(n)]


def test_a_nan_time_is_refused_naming_topic_and_sample(tmp_path: Path) -> None:
    # before: inspect showed a rate of "nan", calibrate joints and sensors exited 0
    msgs = _good()
    msgs[7] = b'{"t_s":NaN,"values":[1,2,256]}'
    p = _mcap(tmp_path / "nan.mcap", msgs)
    with pytest.raises(RecordingError, match=r"nan\.mcap: topic 'raw/acc1': .*t = nan at sample 7 is not a "
                                             r"finite time"):
        read_recording(p)


@pytest.mark.parametrize("value, shown", [("1e23", "1e+23"), ("9223372036854775807", "9223372036854775807"),
                                          ("-2147483649", "-2147483649")])
def test_a_count_beyond_the_feed_is_refused_naming_topic_and_message(tmp_path: Path, value: str,
                                                                       shown: str) -> None:
    msgs = _good()
    msgs[5] = b'{"t_s":0.05,"values":[%s,2,256]}' % value.encode()
    p = _mcap(tmp_path / "big.mcap", msgs)
    with pytest.raises(RecordingError) as e:
        read_recording(p)
    assert str(e.value) == (f"{p}: topic raw/acc1, message 6: acc1_x = {shown} at t = 0.05 s is beyond the "
                            "device's range -2147483648…2147483647; no sensor can have said that, so the "
                            "recording is refused")


@pytest.mark.parametrize("kind, why", [("bogus", "unknown stream kind 'bogus'"),
                                       (None, "no stream metadata (kind, channels)")])
def test_a_sample_topic_the_reader_cannot_take_is_named(tmp_path: Path, kind, why) -> None:
    p = _mcap(tmp_path / "odd.mcap", _good(), kind=kind)
    with pytest.warns(RecordingWarning) as caught:
        rec = read_recording(p)
    assert rec.streams == {}
    assert [str(w.message) for w in caught] == [f"{p}: left out raw/acc1 (20 messages): {why}"]


def test_a_topic_of_its_own_is_not_a_sample_topic_and_is_not_warned_about(tmp_path: Path) -> None:
    p = _mcap(tmp_path / "est.mcap", [b'{"q": 1}'], kind=None, topic="estimates/joints")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RecordingWarning)
        rec = read_recording(p)
    assert rec.meta["read_report"].ignored_topics == ("estimates/joints",)


@pytest.mark.parametrize("payload, shown", [
    (b'{"t_s":0.05,"values":["12",2,256]}', '{"t_s": 0.05, "values": ["12", 2, 256]}'),
    (b'{"t_s":0.05,"values":[true,2,256]}', '{"t_s": 0.05, "values": [true, 2, 256]}'),
    (b'{"t_s":"0.05","values":[1,2,256]}', '{"t_s": "0.05", "values": [1, 2, 256]}'),
    (b'{"t_s":0.05,"values":[null,2,256]}', '{"t_s": 0.05, "values": [null, 2, 256]}'),
])
def test_a_value_that_is_not_a_json_number_is_refused_naming_topic_and_message(
        tmp_path: Path, payload: bytes, shown: str) -> None:
    # before: "12" and true were read as 12 and 1, calibrate joints exited 0 on them
    msgs = _good()
    msgs[5] = payload
    p = _mcap(tmp_path / "str.mcap", msgs)
    with pytest.raises(RecordingError) as e:
        read_recording(p)
    assert str(e.value) == (f"{p}: topic 'raw/acc1': messages do not fit the stream: ValueError: message 6 "
                            f'is not {{"t_s": number, "values": [numbers]}}: {shown}')


def test_two_topics_holding_one_stream_are_refused(tmp_path: Path) -> None:
    # before: the second topic's samples replaced the first's without a word (inspect exited 0)
    p = tmp_path / "two.mcap"
    with open(p, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        meta = {"stream": "acc1", "kind": "accel", "channels": json.dumps(CHANNELS)}
        for topic in ("raw/acc1", "raw/acc2"):
            cid = w.register_channel(topic, "json", sid, meta)
            for i, m in enumerate(_good()):
                w.add_message(cid, i, m, i)
        w.finish()
    with pytest.raises(RecordingError) as e:
        read_recording(p)
    assert str(e.value) == (f"{p}: topics 'raw/acc1' and 'raw/acc2' both hold stream 'acc1'; "
                            "a stream is one topic's")


@pytest.mark.parametrize("keep", [0, 8, 40])
def test_a_damaged_file_with_no_message_left_is_refused_not_summarised_as_empty(tmp_path: Path,
                                                                                keep: int) -> None:
    # before: inspect of an empty file, of the magic alone or of a header cut short exited 0
    # with a recording of 0.00 s
    p = tmp_path / "cut.mcap"
    p.write_bytes(_mcap(tmp_path / "full.mcap", _good()).read_bytes()[:keep])
    with pytest.raises(RecordingError) as e:
        read_recording(p)
    said = str(e.value)
    assert said.startswith(f"{p}: file ends early at byte {keep}")
    assert said.endswith(("recovered 0 messages; the file's summary is missing; no message in it "
                          "could be read", "could not be read; no message in it could be read")), said


def _valid_file(tmp_path: Path) -> bytes:
    t = np.arange(60) * 0.01
    rec = Recording({"acc1": Stream("acc1", "accel", t, np.tile([1, 2, 256], (60, 1)), tuple(CHANNELS)),
                     "enc": Stream("enc", "encoder", t, np.arange(60)[:, None] * [1, -1], ("enc1", "enc2"))})
    write_recording(rec, tmp_path / "valid.mcap")
    return (tmp_path / "valid.mcap").read_bytes()


@settings(derandomize=True, max_examples=120, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(cuts=st.lists(st.tuples(st.floats(0, 1), st.binary(min_size=1, max_size=8)), max_size=4),
       truncate=st.one_of(st.none(), st.floats(0, 1)))
def test_fuzz_a_damaged_file_gives_a_recording_every_door_passes_or_one_clear_error(
        tmp_path: Path, cuts, truncate) -> None:
    data = bytearray(_valid_file(tmp_path))
    for where, junk in cuts:  # bytes overwritten anywhere: headers, chunks, JSON, the footer
        i = int(where * (len(data) - 1))
        data[i:i + len(junk)] = junk
    if truncate is not None:
        data = data[: int(truncate * len(data))]
    p = tmp_path / "fuzz.mcap"
    p.write_bytes(bytes(data))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RecordingWarning)
            rec = read_recording(p)
    except ValueError as e:  # RecordingError, or "not an MCAP file"
        assert str(e).startswith(str(p)) and len(str(e)) < len(str(p)) + 400, str(e)
        return
    assert feed_problems(rec) == []
    for s in rec.streams.values():
        assert s.values.shape == (len(s), len(s.channels)) and np.all(np.diff(s.t_s) > 0)

"""Recording CSV against hostile and broken files: each is refused with a message naming
the place and quoting at most a few dozen characters, within bounded time and memory; a
sample no sensor can have said (a count beyond the feed, a time beyond any clock) is refused
at the door naming its row; fuzzing passes check that nothing else ever escapes the reader."""

from __future__ import annotations

import os
import re
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest
from armfusion.sensors.recording import read_recording
from armfusion.sensors.recording_csv import CsvLimits, RecordingError, RecordingWarning, read_csv
from armfusion.sensors.sample_checks import TIME_LIMIT_S, feed_problems
from armfusion.sensors.samples import Recording
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

HEADER = "t,acc1_x,acc1_y,acc1_z,enc1,enc2\n"


def _rows(n: int, bad_row: int | None = None, bad_cell: str = "") -> str:
    """``n`` good rows; row ``bad_row`` (0-based) has ``bad_cell`` in column acc1_y."""
    out = []
    for i in range(n):
        y = bad_cell if i == bad_row else "-3"
        out.append(f"{i * 0.01:.2f},10,{y},250,{i},7\n")
    return "".join(out)


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def _refusal(path: Path, limits: CsvLimits | None = None) -> tuple[str, float, int]:
    """The reader's message for ``path``, the seconds it took and its peak of traced
    memory in bytes (numpy's arrays included)."""
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(RecordingError) as caught:
            read_csv(path) if limits is None else read_csv(path, limits)
        elapsed = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return str(caught.value), elapsed, peak


def test_a_count_of_ten_to_the_23_is_refused_naming_row_and_column(tmp_path: Path) -> None:
    p = _write(tmp_path / "e23.csv", HEADER + _rows(5, bad_row=2, bad_cell=str(10**23)))
    with pytest.raises(
        RecordingError,
        match=r"e23\.csv: row 3 \(line 4\): column 'acc1_y': '100000000000000000000000' is "
        r"beyond any count \(raw counts are 64-bit integers\)",
    ):
        read_csv(p)
    # the largest 64-bit count still reads
    p = _write(tmp_path / "max.csv", HEADER + _rows(5, bad_row=2, bad_cell=str(2**63 - 1)))
    assert read_csv(p).get("acc1").values[2, 1] == 2**63 - 1


def test_a_20000_digit_cell_is_refused_fast_without_echoing_it(tmp_path: Path) -> None:
    # before: 122 s and 8.2 GB on 20 000 rows (the block was parsed again with every
    # cell 20 000 bytes wide), and a message of 20 099 characters
    p = _write(tmp_path / "d.csv", HEADER + _rows(3000, bad_row=1500, bad_cell="1" * 20_000))
    message, elapsed, peak = _refusal(p)
    assert "d.csv: row 1501 (line 1502): column 'acc1_y': a cell longer than 64 characters" in message
    assert len(message) < 250 + len(str(p))
    assert elapsed < 5.0
    assert peak < 30e6  # the block's cells at 65 bytes at most, not 20 000


def test_a_1_mb_cell_is_refused_at_the_line_without_reading_it_whole(tmp_path: Path) -> None:
    # (the 100 MB cell asked for 3.6 TiB; a line is read 64 kB at most)
    p = _write(tmp_path / "big.csv", HEADER + _rows(10) + "0.5,1," + "7" * 1_000_000 + ",3,4,5\n")
    message, elapsed, peak = _refusal(p)
    assert message.endswith("big.csv: line 12 is longer than 65536 characters (a recording has at "
                            "most 1000 columns of numbers); is it a recording CSV?")
    assert peak < 5e6 and elapsed < 2.0


def test_a_gigabyte_of_nul_padding_is_refused_at_its_first_line(tmp_path: Path) -> None:
    # before: 5.3 GB of memory and 21 s, then a _csv.Error; a sparse file costs no disk
    p = _write(tmp_path / "nul.csv", HEADER + _rows(100))
    os.truncate(p, p.stat().st_size + 2**30)
    message, elapsed, peak = _refusal(p)
    assert message == f"{p}: line 102 holds a NUL byte; a recording CSV is text"
    assert peak < 5e6 and elapsed < 2.0


def test_a_file_beyond_the_size_limit_is_refused_unread(tmp_path: Path) -> None:
    p = _write(tmp_path / "huge.csv", HEADER + _rows(10))
    os.truncate(p, 3 * 2**30)  # sparse: 3 GB that are not on the disk
    message, elapsed, _ = _refusal(p)
    assert message == f"{p}: 3221 MB is more than the reader takes (2147 MB); split the recording"
    assert elapsed < 0.5
    # the limit is a public parameter: a small one is met by a small file
    p = _write(tmp_path / "small.csv", HEADER + _rows(100))
    with pytest.raises(RecordingError, match=r"0 MB is more than the reader takes \(0 MB\)"):
        read_csv(p, CsvLimits(max_file_bytes=1000))
    assert len(read_csv(p, CsvLimits(max_file_bytes=p.stat().st_size)).get("acc1")) == 100


def test_a_header_of_a_million_columns_is_refused_in_well_under_a_second(tmp_path: Path) -> None:
    # before: still running after 180 s (a quadratic search for repeated names)
    p = _write(tmp_path / "wide.csv",
               "t,acc1_x,acc1_y,acc1_z," + ",".join(f"u{i}" for i in range(10**6)) + "\n0,1,2,3\n")
    message, elapsed, peak = _refusal(p)
    assert message == (f"{p}: the header row is longer than 65536 characters (a recording has "
                       "at most 1000 columns of numbers); is it a recording CSV?")
    assert elapsed < 1.0 and peak < 5e6


def test_a_header_of_ten_thousand_columns_is_refused_by_count(tmp_path: Path) -> None:
    # 10^4 short names fit in a line; before: read in 3 s with 89 kB of warnings
    cols = ",".join(f"u{i}" for i in range(10**4))
    p = _write(tmp_path / "w.csv", f"t,{cols}\n0{',' * 10**4}\n")
    with pytest.raises(RecordingError, match=r"w\.csv: the header has 10001 columns; the reader "
                                             r"takes at most 1000 \(is it a recording CSV\?\)"):
        read_csv(p)


def test_hundreds_of_unknown_columns_are_summarised_in_one_short_warning(tmp_path: Path) -> None:
    cols = ",".join(f"unknown_column_{i}" for i in range(900))
    p = _write(tmp_path / "u.csv", f"t,acc1_x,acc1_y,acc1_z,{cols}\n0,1,2,3{',' * 900}\n")
    with pytest.warns(RecordingWarning) as caught:
        rec = read_csv(p)
    assert len(caught) == 1
    message = str(caught[0].message)
    assert "ignored 900 unknown column(s): 'unknown_column_0', 'unknown_column_1'" in message
    assert message.endswith("'unknown_column_7', … and 892 more")
    assert len(message) < 300 + len(str(p))
    assert rec.get("acc1").values.tolist() == [[1, 2, 3]]


def test_the_cell_limit_applies_to_used_columns_and_is_a_parameter(tmp_path: Path) -> None:
    note = "the arm was bumped by the caregiver " * 4  # 140 characters of text
    p = _write(tmp_path / "n.csv", f"t,acc1_x,acc1_y,acc1_z,note\n0,1,2,3,{note}\n0.01,1,2,3,\n")
    with pytest.warns(RecordingWarning, match=r"ignored 1 unknown column\(s\): 'note'"):
        assert len(read_csv(p).get("acc1")) == 2
    p = _write(tmp_path / "c.csv", HEADER + _rows(3, bad_row=1, bad_cell="1" * 11))
    with pytest.raises(RecordingError, match=r"row 2 \(line 3\): column 'acc1_y': a cell longer "
                                             r"than 10 characters \(it starts '11111111111'\)"):
        read_csv(p, CsvLimits(max_cell_chars=10))
    p = _write(tmp_path / "c.csv", HEADER + _rows(3, bad_row=1, bad_cell="1" * 10))
    assert read_csv(p, CsvLimits(max_cell_chars=10)).get("acc1").values[1, 1] == 1111111111


def test_memory_stays_a_small_multiple_of_the_file_plus_a_fixed_block(tmp_path: Path) -> None:
    # what the reader keeps is ~9 B a used cell (its value, and whether it was empty);
    # what it parses at once is one block of at most 2^19 cells (~50 MB)
    rng = np.random.default_rng(3)
    n = 40_000
    counts = rng.integers(-512, 512, (n, 5))
    text = HEADER + "".join(f"{i * 0.01:.2f},{a},{b},{c},{d},{e}\n"
                            for i, (a, b, c, d, e) in enumerate(counts.tolist()))
    p = _write(tmp_path / "ok.csv", text)
    tracemalloc.start()
    try:
        rec = read_csv(p)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(rec.get("enc").values, counts[:, 3:])
    assert peak < 4 * p.stat().st_size + 50e6  # a 1.1 MB file


@pytest.mark.parametrize("cell, kind", [("Ðé", "an integer \\(raw counts\\)"),
                                        ("\U0005afd5x", "a number")])
def test_a_cell_of_letters_outside_ascii_is_quoted_as_written(tmp_path: Path, cell: str, kind: str) -> None:
    p = _write(tmp_path / "u.csv", HEADER + _rows(3, bad_row=1, bad_cell=cell))
    with pytest.raises(RecordingError, match=rf"u\.csv: row 2 \(line 3\): column 'acc1_y': "
                                             rf"{re.escape(repr(cell))} is not {kind}"):
        read_csv(p)


# ---------------------------------------------------------------------------- row widths


def test_a_row_with_an_extra_cell_is_refused_like_a_short_one(tmp_path: Path) -> None:
    p = _write(tmp_path / "x.csv", "t,acc1_x,acc1_y,acc1_z\n0.0,1,2,3\n0.1,1,2,3,4\n")
    with pytest.raises(RecordingError, match=r"x\.csv: row 2 \(line 3\): 5 cells, but the "
                                             r"header has 4 columns"):
        read_csv(p)


@pytest.mark.parametrize("shifted", [1, 400])
def test_a_cell_inserted_after_t_is_refused_naming_the_first_row(tmp_path: Path, shifted: int) -> None:
    lines = _rows(1000).splitlines(keepends=True)
    for k in range(500, 500 + shifted):  # every later cell moves one column right
        t, rest = lines[k].split(",", 1)
        lines[k] = f"{t},0,{rest}"
    p = _write(tmp_path / "s.csv", HEADER + "".join(lines))
    with pytest.raises(RecordingError, match=r"s\.csv: row 501 \(line 502\): 7 cells, but the "
                                             r"header has 6 columns"):
        read_csv(p)


def test_a_quoted_comma_is_one_cell_not_an_extra_one(tmp_path: Path) -> None:
    p = _write(tmp_path / "q.csv", 't,acc1_x,acc1_y,acc1_z,note\n0,1,2,3,"moved, slowly"\n')
    with pytest.warns(RecordingWarning):
        assert read_csv(p).get("acc1").values.tolist() == [[1, 2, 3]]


def test_a_sensor_missing_one_axis_is_said_to_be_incomplete(tmp_path: Path) -> None:
    p = _write(tmp_path / "a.csv", "t,acc1_x,acc1_y,acc1_z,acc2_x,acc2_z\n0,1,2,3,4,5\n")
    with pytest.warns(RecordingWarning) as caught:
        rec = read_csv(p)
    message = str(caught[0].message)
    assert message == (f"{p}: incomplete sensor(s) left out: acc2 (has acc2_x, acc2_z; needs "
                       "acc2_y too)")
    assert sorted(rec.streams) == ["acc1"]


# ---------------------------------------------------------------------------- fuzzing

_GROUPS = [("acc1_x", "acc1_y", "acc1_z"), ("acc2_x", "acc2_z"), ("enc1", "enc2"), ("enc3",),
           ("imu_mx", "imu_my", "imu_mz"), ("imu_temp",), ("true_q1",), ("true_roll",),
           ("note",), ("",), ("acc1_y ",)]
_HOSTILE_CELLS = st.one_of(
    st.integers(-(2**70), 2**70).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from([" ", "nan", "-", "+", "1e400", "0x10", "1_000", '"', '"1,2"', "\0",
                     "\ufeff", "é", "1" * 80, "\r", "'"]),
    st.text(max_size=6),
)
# mostly a count, sometimes empty, now and then something hostile
_CELLS = st.integers(0, 19).flatmap(
    lambda k: st.integers(-600, 600).map(str) if k < 15 else st.just("") if k < 18 else _HOSTILE_CELLS)
_LIMITS = CsvLimits(max_file_bytes=50_000, max_columns=12, max_cell_chars=40, max_line_chars=300)


@st.composite
def _files(draw) -> bytes:
    """Mostly near-valid recordings (a header starting with t, known column groups,
    increasing times, small counts) with hostile cells, widths and bytes mixed in."""
    if draw(st.integers(0, 19)) == 0:  # sometimes just bytes
        return draw(st.binary(max_size=300))
    groups = draw(st.lists(st.sampled_from(_GROUPS), max_size=6, unique=True))
    header = ["t"] + [c for g in groups for c in g]
    if draw(st.integers(0, 9)) == 0:  # t elsewhere, or twice
        header = draw(st.permutations(header + draw(st.sampled_from([[], ["t"]]))))
    n_rows = draw(st.integers(0, 8))
    rows = []
    for k in range(n_rows):
        width = len(header) + draw(st.sampled_from([0] * 8 + [-1, 1]))
        cells = [draw(_CELLS) for _ in range(max(width, 0))]
        if cells and draw(st.integers(0, 9)) < 8:
            cells[0] = f"{k * 0.01:.2f}"  # a proper time, mostly
        rows.append(",".join(cells))
    newline = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    return newline.join([",".join(header), *rows]).encode("utf-8", "surrogatepass")


@settings(derandomize=True, max_examples=300, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=_files(), small=st.booleans())
def test_fuzz_the_reader_returns_a_recording_or_its_own_clear_error(
    tmp_path: Path, data: bytes, small: bool
) -> None:
    p = tmp_path / "fuzz.csv"
    p.write_bytes(data)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RecordingWarning)
            rec = read_csv(p, _LIMITS) if small else read_csv(p)
    except RecordingError as e:
        message = str(e)
        assert message.startswith(str(p))
        assert len(message) < len(str(p)) + 300, message  # quotes values short
        return
    assert isinstance(rec, Recording)
    for s in rec.streams.values():
        assert np.all(np.diff(s.t_s) > 0) and s.values.shape == (len(s.t_s), len(s.channels))


# ---------------------------------------------------------------------------- the admission
# every reader's (armfusion.sensors.sample_checks): what no sensor can have said is refused at the door,
# naming the row and line, in the words the fusion node uses for the same sample


def _read(path: Path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordingWarning)
        return read_recording(path)


@pytest.mark.parametrize("cell, shown", [
    (str(2**63 - 1), "9223372036854775807"), (str(-(2**63)), "-9223372036854775808"),
    ("1e308", "1e+308"), (str(2**31), "2147483648"), (str(-(2**31) - 1), "-2147483649")])
def test_a_count_beyond_the_feeds_int32_is_refused_naming_row_line_and_stream(
        tmp_path: Path, cell: str, shown: str) -> None:
    rows = _rows(5).splitlines(keepends=True)
    cells = rows[2].split(",")
    cells[4] = cell  # enc1 of row 3
    rows[2] = ",".join(cells)
    p = _write(tmp_path / "enc.csv", HEADER + "".join(rows))
    with pytest.raises(RecordingError) as e:
        _read(p)
    assert str(e.value) == (f"{p}: row 3 (line 4), stream enc: enc1 = {shown} at t = 0.02 s is beyond the "
                            "device's range -2147483648…2147483647; no sensor can have said that, so the "
                            "recording is refused")


def test_the_feeds_own_limits_are_read(tmp_path: Path) -> None:
    rows = _rows(5).replace("\n0.02,10,-3,250,2,7", f"\n0.02,10,-3,250,{2**31 - 1},7")
    rows = rows.replace("\n0.03,10,-3,250,3,7", f"\n0.03,10,-3,250,{-(2**31)},7")
    rec = _read(_write(tmp_path / "limits.csv", HEADER + rows))
    assert rec.get("enc").values[2:4, 0].tolist() == [2**31 - 1, -(2**31)]


@pytest.mark.parametrize("t_last, words", [
    ("1e308", "t = 1e+308 s is beyond any sensor's clock"),
    ("4.6e9", "t = 4.6e+09 s is beyond any sensor's clock"),
    ("1e9", "t = 1e+09 s begins a run of 1 instant(s) more than 2 s apart from the rest of the recording "
            "(its 40 instants at t = 0 … 0.39 s): not on the sensors' clock")])
def test_a_time_beyond_reason_is_refused_naming_its_row(tmp_path: Path, t_last: str, words: str) -> None:
    # before: 1e308 was an OverflowError in inspect, replay, calibrate joints and track; 1e9 a
    # MemoryError (the still detection's grid over 10^9 s)
    p = _write(tmp_path / "late.csv", HEADER + _rows(40) + f"{t_last},10,-3,250,40,7\n")
    with pytest.raises(RecordingError) as e:
        _read(p)
    assert str(e.value).startswith(f"{p}: row 41 (line 42), stream acc1: {words}")


@pytest.mark.parametrize("cell, shown", [("inf", "inf"), ("1e308", "1e+308"), ("-1e308", "-1e+308")])
def test_a_ground_truth_that_is_no_angle_is_refused_naming_its_row(tmp_path: Path, cell: str,
                                                                    shown: str) -> None:
    # before: read, and track printed numpy's overflow warnings over its RMS errors against it
    rows = "".join(f"{i * 0.01:.2f},10,-3,250,{cell if i == 20 else '0.5'}\n" for i in range(40))
    p = _write(tmp_path / "truth.csv", "t,acc1_x,acc1_y,acc1_z,true_q1\n" + rows)
    with pytest.raises(RecordingError) as e:
        _read(p)
    assert str(e.value) == (f"{p}: row 21 (line 22), stream true_q: true_q1 = {shown} rad at t = 0.2 s "
                            "is not an angle (its degrees are not a finite number); no ground truth can be "
                            "that, so the recording is refused")


@settings(derandomize=True, max_examples=80, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(angle=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from(["", "1e309", "-0"])))
def test_fuzz_a_ground_truth_read_is_an_angle_or_a_gap(tmp_path: Path, angle) -> None:
    rows = "".join(f"{i * 0.01:.2f},10,-3,250,{angle if i == 3 else 0.5}\n" for i in range(10))
    p = _write(tmp_path / "truth.csv", "t,acc1_x,acc1_y,acc1_z,true_q1\n" + rows)
    try:
        rec = _read(p)
    except RecordingError as e:
        assert str(e).startswith(f"{p}: row 4 (line 5), stream true_q: true_q1 = "), str(e)
        return
    q = rec.get("true_q").values
    with np.errstate(over="raise"):
        assert np.all(np.isnan(q) | np.isfinite(np.degrees(q)))


def test_times_in_another_unit_than_the_second_are_refused(tmp_path: Path) -> None:
    # before: a recording stamped in 10 ps steps (its times scaled by 1e-9) was read, and
    # `calibrate sensors` and `diagnose` exited 0 on it
    rows = "".join(f"{i * 1e-11!r},10,-3,250,{i},7\n" for i in range(40))
    p = _write(tmp_path / "dense.csv", HEADER + rows)
    with pytest.raises(RecordingError) as e:
        _read(p)
    assert str(e.value).startswith(f"{p}: row 2 (line 3), stream acc1: a sample every 1e-11 s (the stream's "
                                   "median step), faster than any sensor delivers (100 kHz at most): are its "
                                   "times in seconds?")
    fast = "".join(f"{i * 1.25e-4!r},10,-3,250,{i},7\n" for i in range(40))  # 8 kHz: a gyro's fastest
    assert len(_read(_write(tmp_path / "fast.csv", HEADER + fast)).get("acc1")) == 40


def test_a_recording_with_a_long_pause_and_much_after_it_is_read(tmp_path: Path) -> None:
    # a logger paused for an hour: 40 instants, then 40 more; only a short run apart is refused
    later = "".join(f"{3600 + i * 0.01:.2f},10,-3,250,{i},7\n" for i in range(40))
    rec = _read(_write(tmp_path / "pause.csv", HEADER + _rows(40) + later))
    assert len(rec.get("acc1")) == 80 and rec.t_end_s == pytest.approx(3600.39)


@pytest.mark.parametrize("column, row", [(1, "0.01,2_59,-3,250,1,7"), (0, "0_1,10,-3,250,1,7"),
                                         (1, "0.01,2_5.9,-3,250,1,7")])
def test_digit_grouping_is_not_a_number_of_a_csv(tmp_path: Path, column: int, row: str) -> None:
    # Python's literal syntax (int("2_59") == 259), not a number a CSV writes
    text = HEADER + "0.00,10,-3,250,0,7\n" + row + "\n0.02,10,-3,250,2,7\n"
    p = _write(tmp_path / "grouped.csv", text)
    with pytest.raises(RecordingError, match=r"row 2 \(line 3\): column '(t|acc1_x)': '[0-9_.]+' is not"):
        read_csv(p)


def test_a_fifo_is_refused_without_blocking(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    t0 = time.perf_counter()
    with pytest.raises(RecordingError, match=r"pipe\.csv: not a regular file"):
        read_recording(fifo)
    assert time.perf_counter() - t0 < 1.0


_TIMES = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr),
                   st.sampled_from(["1e308", "1e9", "4.6e9", "-1e300", "2_59"]))
_COUNTS = st.one_of(st.integers(-(2**64), 2**64).map(str), st.sampled_from(["1e308", "2147483648", "-0"]))


@st.composite
def _admission_files(draw) -> bytes:
    """A valid recording of ``HEADER`` with, now and then, a hostile time or count in a row."""
    n = draw(st.integers(1, 30))
    rows = []
    for i in range(n):
        t = draw(_TIMES) if draw(st.integers(0, 9)) == 0 else f"{i * 0.01:.2f}"
        enc = draw(_COUNTS) if draw(st.integers(0, 9)) == 0 else str(i)
        rows.append(f"{t},10,-3,250,{enc},7")
    return (HEADER + "\n".join(rows) + "\n").encode()


@settings(derandomize=True, max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=_admission_files())
def test_fuzz_what_read_recording_returns_passes_every_doors_rules(tmp_path: Path, data: bytes) -> None:
    p = tmp_path / "fuzz.csv"
    p.write_bytes(data)
    try:
        rec = _read(p)
    except RecordingError as e:
        assert str(e).startswith(f"{p}: row ") or str(e).startswith(f"{p}: the file"), str(e)
        return
    assert feed_problems(rec) == []
    for s in rec.streams.values():
        assert np.all(np.isfinite(s.t_s)) and np.all(np.abs(s.t_s) <= TIME_LIMIT_S)
        if s.kind == "encoder":
            assert np.all(np.abs(s.values.astype(float)) <= 2**31)

"""Recording CSV (shared/spec/recording-csv.md): round trip, foreign files, errors."""

from __future__ import annotations

import csv
import warnings
from pathlib import Path

import numpy as np
import pytest
from armfusion.sensors.recording_csv import RecordingWarning, read_csv, write_csv
from armfusion.sensors.samples import (
    IMU_STREAMS,
    TRUTH_BASE_COLUMNS,
    Recording,
    Stream,
    accel_columns,
    encoder_columns,
    truth_joint_columns,
)
from hypothesis import given, settings
from hypothesis import strategies as st


def _recording(seed: int = 0, duration_s: float = 3.0) -> Recording:
    """Every stream kind, at different rates, with a negative time origin.

    Link accelerometers, IMU and truth at 100 Hz; magnetometer at 10 Hz (a subset of
    the same instants); temperature at 1 Hz; encoders at 100 Hz but half a period
    later, so their rows interleave with the others.
    """
    rng = np.random.default_rng(seed)
    t = -2.0 + np.arange(int(duration_s * 100)) * 0.01
    n = t.size

    def counts(m: int, k: int, scale: int) -> np.ndarray:
        return rng.integers(-scale, scale, size=(m, k))

    s = [Stream(f"acc{i}", "accel", t, counts(n, 3, 512), accel_columns(f"acc{i}")) for i in (1, 2)]
    for name, (kind, cols) in IMU_STREAMS.items():
        if name == "imu_mag":
            s.append(Stream(name, kind, t[::10], counts(n // 10 + (n % 10 > 0), 3, 300), cols))
        elif name == "imu_temp":
            s.append(Stream(name, kind, t[::100], counts(len(t[::100]), 1, 9000), cols))
        else:
            s.append(Stream(name, kind, t, counts(n, 3, 32768), cols))
    s.append(Stream("enc", "encoder", t + 0.005, counts(n, 7, 10**9), encoder_columns(7)))
    s.append(
        Stream("true_q", "truth_joints", t, rng.uniform(-3, 3, (n, 7)), truth_joint_columns(7))
    )
    s.append(Stream("true_base", "truth_base", t, rng.normal(0, 0.1, (n, 3)), TRUTH_BASE_COLUMNS))
    return Recording({x.name: x for x in s})


def _write_rows(path: Path, rows: list[list[str]]) -> None:
    """A CSV 'from another program': the csv module's defaults, CRLF line endings."""
    with open(path, "w", newline="", encoding="utf-8") as f:
        csv.writer(f).writerows(rows)


def _read_quietly(path: Path) -> Recording:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return read_csv(path)


# ---------------------------------------------------------------------------- round trip


def test_round_trip_gives_back_every_stream(tmp_path: Path) -> None:
    rec = _recording()
    write_csv(rec, tmp_path / "r.csv")
    back = _read_quietly(tmp_path / "r.csv")

    assert list(back.streams) == list(rec.streams)
    for name, s in rec.streams.items():
        b = back.streams[name]
        assert (b.kind, b.channels) == (s.kind, s.channels)
        # t is written as the shortest text that reads back to the same float
        np.testing.assert_array_equal(b.t_s, s.t_s)
        if s.kind.startswith("truth"):
            # 10 significant digits: relative error below 5e-10
            np.testing.assert_allclose(b.values, s.values, rtol=5e-10, atol=1e-300)
        else:
            assert b.values.dtype == np.int64
            np.testing.assert_array_equal(b.values, s.values)
    assert back.get("imu_mag").rate_hz == pytest.approx(10.0)
    assert back.get("imu_temp").rate_hz == pytest.approx(1.0)
    assert back.t_start_s == -2.0


def test_writer_merges_streams_onto_the_union_of_instants(tmp_path: Path) -> None:
    rec = _recording(duration_s=0.05)
    write_csv(rec, tmp_path / "r.csv")
    lines = (tmp_path / "r.csv").read_text().splitlines()
    header = lines[0].split(",")
    assert header[:4] == ["t", "acc1_x", "acc1_y", "acc1_z"]
    rows = [dict(zip(header, line.split(","), strict=True)) for line in lines[1:]]
    # 5 instants of the 100 Hz sensors, 5 more half a period later for the encoders
    assert [r["t"] for r in rows[:4]] == ["-2.0", "-1.995", "-1.99", "-1.985"]
    assert rows[0]["enc1"] == "" and rows[0]["imu_mx"] != "" and rows[0]["imu_temp"] != ""
    assert rows[1]["enc1"] != "" and rows[1]["acc1_x"] == "" and rows[1]["true_q1"] == ""
    assert rows[2]["imu_mx"] == "" and rows[2]["imu_ax"] != ""


def test_an_empty_recording_round_trips_to_a_header_only_file(tmp_path: Path) -> None:
    rec = Recording({"acc1": Stream("acc1", "accel", [], np.zeros((0, 3)), accel_columns("acc1"))})
    write_csv(rec, tmp_path / "r.csv")
    assert (tmp_path / "r.csv").read_text() == "t,acc1_x,acc1_y,acc1_z\n"
    back = _read_quietly(tmp_path / "r.csv")
    assert len(back.get("acc1")) == 0 and back.get("acc1").values.shape == (0, 3)


def test_writer_refuses_a_stream_the_format_cannot_name(tmp_path: Path) -> None:
    gyro = Stream("gyro", "gyro", [0.0], [[1, 2, 3]], ("gx", "gy", "gz"))
    with pytest.raises(ValueError, match="only as stream 'imu_gyro'"):
        write_csv(Recording({"gyro": gyro}), tmp_path / "r.csv")
    acc = Stream("acc1", "accel", [0.0], [[1, 2, 3]], ("x", "y", "z"))
    with pytest.raises(ValueError, match=r"the recording CSV names them \['acc1_x'"):
        write_csv(Recording({"acc1": acc}), tmp_path / "r.csv")


# ---------------------------------------------------------------------------- foreign files


def test_reads_a_file_written_by_another_program(tmp_path: Path) -> None:
    """Different column order, extra columns, sensors at different rates, CRLF."""
    header = (
        ["enc2", "note", "imu_gz", "imu_gy", "imu_gx", "acc2_z", "acc2_y", "acc2_x", "t"]
        + ["enc1", "imu_ax", "imu_ay", "imu_az", "acc9_x", "true_q1", "true_q2"]
    )
    rng = np.random.default_rng(7)
    rows = [header]
    expected: dict[str, list] = {"acc2": [], "imu_gyro": [], "imu_acc": [], "enc": [], "tq": []}
    for k in range(200):  # 200 Hz base clock, 1 s
        t = round(10.0 + k * 0.005, 6)
        cells = dict.fromkeys(header, "")
        cells["t"] = f"{t:.6f}"
        cells["note"] = "moving, slowly" if k == 3 else ""
        if k % 2 == 0:  # gyro 100 Hz
            g = rng.integers(-30000, 30000, 3)
            cells.update(imu_gx=str(g[0]), imu_gy=str(g[1]), imu_gz=str(g[2]))
            expected["imu_gyro"].append((t, g))
            a = rng.integers(-20000, 20000, 3)
            cells.update(imu_ax=str(a[0]), imu_ay=str(a[1]), imu_az=str(a[2]))
            expected["imu_acc"].append((t, a))
        if k % 4 == 0:  # link accelerometer 50 Hz
            a = rng.integers(-512, 512, 3)
            cells.update(acc2_x=str(a[0]), acc2_y=str(a[1]), acc2_z=str(a[2]))
            expected["acc2"].append((t, a))
        if k % 20 == 0:  # encoders 10 Hz
            e = rng.integers(-(10**6), 10**6, 2)
            cells.update(enc1=str(e[0]), enc2=str(e[1]))
            expected["enc"].append((t, e))
        cells["acc9_x"] = "5"
        q = rng.uniform(-1, 1, 2)  # truth at 200 Hz
        cells.update(true_q1=repr(float(q[0])), true_q2=repr(float(q[1])))
        expected["tq"].append((t, q))
        rows.append([cells[h] for h in header])
    _write_rows(tmp_path / "other.csv", rows)
    assert b"\r\n" in (tmp_path / "other.csv").read_bytes()

    with pytest.warns(RecordingWarning) as caught:
        rec = read_csv(tmp_path / "other.csv")
    assert len(caught) == 1
    message = str(caught[0].message)
    assert "incomplete sensor(s) left out: acc9 (has acc9_x; needs acc9_y, acc9_z too)" in message
    assert "ignored 1 unknown column(s): 'note'" in message

    assert sorted(rec.streams) == ["acc2", "enc", "imu_acc", "imu_gyro", "true_q"]
    assert rec.get("acc2").rate_hz == pytest.approx(50.0)
    assert rec.get("imu_gyro").rate_hz == pytest.approx(100.0)
    assert rec.get("enc").rate_hz == pytest.approx(10.0)
    assert rec.get("true_q").rate_hz == pytest.approx(200.0)
    assert rec.get("enc").channels == ("enc1", "enc2")
    assert rec.get("imu_gyro").channels == ("imu_gx", "imu_gy", "imu_gz")
    assert rec.get("acc2").channels == ("acc2_x", "acc2_y", "acc2_z")
    for name, stream_name in [("acc2", "acc2"), ("imu_gyro", "imu_gyro"), ("enc", "enc")]:
        t_exp = np.array([t for t, _ in expected[name]])
        v_exp = np.array([v for _, v in expected[name]])
        np.testing.assert_array_equal(rec.get(stream_name).t_s, t_exp)
        np.testing.assert_array_equal(rec.get(stream_name).values, v_exp)
    np.testing.assert_array_equal(rec.get("true_q").values, [q for _, q in expected["tq"]])


def test_tolerates_spaces_blank_lines_a_bom_and_wide_cells(tmp_path: Path) -> None:
    text = (
        "\ufefft, acc1_x, acc1_y, acc1_z, enc1\n"
        "\n"
        "0.0, 1, -2, +3, 10\n"
        "0.1000000000000000000000000000000000001, , , , 11\n"
        "   \n"
        "0.2, 4, 5, 6,\n"
    )
    (tmp_path / "h.csv").write_text(text, encoding="utf-8")
    rec = _read_quietly(tmp_path / "h.csv")
    np.testing.assert_array_equal(rec.get("acc1").values, [[1, -2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(rec.get("acc1").t_s, [0.0, 0.2])
    np.testing.assert_array_equal(rec.get("enc").t_s, [0.0, 0.1])
    np.testing.assert_array_equal(rec.get("enc").values, [[10], [11]])


def test_incomplete_known_groups_are_ignored_with_the_reason(tmp_path: Path) -> None:
    _write_rows(
        tmp_path / "g.csv",
        [["t", "imu_mx", "imu_my", "enc2", "true_roll"], ["0", "1", "2", "3", "0.5"]],
    )
    with pytest.warns(RecordingWarning) as caught:
        rec = read_csv(tmp_path / "g.csv")
    message = str(caught[0].message)
    assert "imu_mag (has imu_mx, imu_my; needs imu_mz too)" in message
    assert "enc2 (enc1..N must be contiguous from 1)" in message
    assert "true_base (has true_roll; needs true_pitch, true_yaw too)" in message
    assert "unknown" not in message
    assert rec.streams == {}


# ---------------------------------------------------------------------------- errors


def _acc_file(path: Path, body: list[list[str]]) -> Path:
    _write_rows(path, [["t", "acc1_x", "acc1_y", "acc1_z"], *body])
    return path


def test_time_going_backwards_names_the_row_line_and_values(tmp_path: Path) -> None:
    p = _acc_file(
        tmp_path / "b.csv",
        [["0.00", "1", "2", "3"], ["0.02", "1", "2", "3"], ["0.01", "1", "2", "3"]],
    )
    with pytest.raises(
        ValueError,
        match=r"b\.csv: row 3 \(line 4\): t must increase from row to row, but "
        r"t = 0\.01 follows t = 0\.02 at row 2 \(line 3\)",
    ):
        read_csv(p)


def test_a_repeated_time_is_rejected(tmp_path: Path) -> None:
    p = _acc_file(tmp_path / "b.csv", [["0.5", "1", "2", "3"], ["0.5", "", "", ""]])
    with pytest.raises(ValueError, match=r"row 2 \(line 3\): t must increase"):
        read_csv(p)


@pytest.mark.parametrize("value", ["abc", "0x10", "12a"])
def test_a_raw_cell_that_is_not_a_number_names_file_row_column_value(
    tmp_path: Path, value: str
) -> None:
    p = _acc_file(tmp_path / "c.csv", [["0.0", "1", "2", "3"], ["0.1", "4", value, "6"]])
    with pytest.raises(
        ValueError,
        match=rf"c\.csv: row 2 \(line 3\): column 'acc1_y': '{value}' is not an integer \(raw "
        r"counts\) or a decimal",
    ):
        read_csv(p)


@pytest.mark.parametrize("value", ["nan", "inf", "-Infinity"])
def test_a_raw_cell_that_is_not_finite_is_refused_saying_how_to_mark_a_gap(
    tmp_path: Path, value: str
) -> None:
    p = _acc_file(tmp_path / "c.csv", [["0.0", "1.5", "2", "3"], ["0.1", "4", value, "6"]])
    with pytest.raises(ValueError, match=rf"row 2 \(line 3\): column 'acc1_y': '{value}' is not a "
                                         r"finite value \(leave the cell empty"):
        read_csv(p)


def test_decimal_raw_values_are_read_as_floats_and_whole_ones_stay_integer_counts(tmp_path: Path) -> None:
    # a sensor delivering g rounded to 0.01 (beyond the spec's integer counts), and the
    # same file's encoder column of integers, read exactly
    p = tmp_path / "g.csv"
    p.write_text("t,acc1_x,acc1_y,acc1_z,enc1\n0.0,0.07,0.82,-0.03,5\n0.01,,,,7\n"
                 "0.02,0.1,0.2,0.3,9007199254740993\n")
    rec = read_csv(p)
    acc, enc = rec.get("acc1"), rec.get("enc")
    assert acc.values.dtype == np.float64 and enc.values.dtype == np.int64
    np.testing.assert_array_equal(acc.values, [[0.07, 0.82, -0.03], [0.1, 0.2, 0.3]])
    np.testing.assert_array_equal(acc.t_s, [0.0, 0.02])
    assert enc.values[:, 0].tolist() == [5, 7, 9007199254740993]  # past 2**53: not through a float
    whole = tmp_path / "w.csv"
    whole.write_text("t,acc1_x,acc1_y,acc1_z\n0.0,1.0,2,3e0\n0.1,1e3,12.0,-0\n")
    back = read_csv(whole).get("acc1").values
    assert back.dtype == np.int64 and back.tolist() == [[1, 2, 3], [1000, 12, 0]]  # whole: counts


def test_a_time_that_is_not_a_number_is_named(tmp_path: Path) -> None:
    p = _acc_file(tmp_path / "c.csv", [["0.0", "1", "2", "3"], ["zero", "4", "5", "6"]])
    with pytest.raises(ValueError, match=r"row 2 \(line 3\): column 't': 'zero' is not a number"):
        read_csv(p)


def test_a_row_filling_only_part_of_a_stream_is_an_error(tmp_path: Path) -> None:
    p = _acc_file(tmp_path / "p.csv", [["0.0", "1", "2", "3"], ["0.1", "4", "5", ""]])
    with pytest.raises(
        ValueError,
        match=r"p\.csv: row 2 \(line 3\): stream 'acc1' has acc1_x, acc1_y but column\(s\) "
        r"acc1_z empty",
    ):
        read_csv(p)


def test_an_empty_time_is_an_error(tmp_path: Path) -> None:
    p = _acc_file(tmp_path / "e.csv", [["0.0", "1", "2", "3"], ["", "4", "5", "6"]])
    with pytest.raises(ValueError, match=r"row 2 \(line 3\): t is empty"):
        read_csv(p)


def test_a_row_with_a_different_number_of_cells_is_named(tmp_path: Path) -> None:
    p = tmp_path / "r.csv"
    p.write_text("t,acc1_x,acc1_y,acc1_z\n0.0,1,2,3\n0.1,1,2\n")
    with pytest.raises(ValueError, match=r"row 2 \(line 3\): 3 cells, but the header has 4"):
        read_csv(p)


def test_missing_time_column_and_empty_file(tmp_path: Path) -> None:
    p = tmp_path / "n.csv"
    p.write_text("time,acc1_x,acc1_y,acc1_z\n0.0,1,2,3\n")
    with pytest.raises(ValueError, match=r"n\.csv: no column 't' in the header"):
        read_csv(p)
    p.write_text("")
    with pytest.raises(ValueError, match=r"n\.csv: the file is empty"):
        read_csv(p)


def test_a_binary_file_is_not_taken_for_a_csv(tmp_path: Path) -> None:
    p = tmp_path / "run.csv"
    p.write_bytes(b"\x89MCAP0\r\n\x01\xff\xfe\x00")
    with pytest.raises(ValueError, match=r"run\.csv: not UTF-8 text"):
        read_csv(p)


def test_decimal_raw_values_and_a_link_gyro_round_trip_exactly_through_the_csv(tmp_path: Path) -> None:
    rng = np.random.default_rng(12)
    t = np.arange(300) * 0.01
    g = np.round(rng.normal(0.0, 1.0, (300, 3)), 2)
    dps = rng.normal(0.0, 50.0, (150, 3))  # every bit of the float, on every other row
    rec = Recording({
        "shaft": Stream("shaft", "accel", t, g, accel_columns("shaft")),
        "shaft_gyro": Stream("shaft_gyro", "link_gyro", t[::2], dps, ("shaft_gx", "shaft_gy", "shaft_gz")),
        "enc": Stream("enc", "encoder", t, rng.integers(-(10**6), 10**6, (300, 1)), ("enc1",)),
    })
    write_csv(rec, tmp_path / "r.csv")
    assert (tmp_path / "r.csv").read_text().splitlines()[0] == (
        "t,shaft_x,shaft_y,shaft_z,shaft_gx,shaft_gy,shaft_gz,enc1")
    back = read_csv(tmp_path / "r.csv")
    for name, s in rec.streams.items():
        assert back.get(name).kind == s.kind and back.get(name).values.dtype == s.values.dtype
        np.testing.assert_array_equal(back.get(name).values, s.values)
        np.testing.assert_array_equal(back.get(name).t_s, s.t_s)


def test_a_link_gyro_with_a_column_missing_is_left_out_and_named(tmp_path: Path) -> None:
    p = tmp_path / "g.csv"
    p.write_text("t,shaft_gx,shaft_gz,imu_gx,imu_gy,imu_gz\n0.0,1,2,3,4,5\n")
    with pytest.warns(RecordingWarning, match=r"shaft_gyro \(has shaft_gx, shaft_gz; needs shaft_gy too\)"):
        rec = read_csv(p)
    assert set(rec.streams) == {"imu_gyro"}


_FINITE = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(derandomize=True, max_examples=60, deadline=None)
@given(st.lists(st.tuples(_FINITE, _FINITE, _FINITE), min_size=1, max_size=20))
def test_any_finite_raw_values_read_back_bit_for_bit_from_both_formats(tmp_path_factory, rows) -> None:
    from armfusion.sensors.recording_mcap import read_mcap, write_mcap

    values = np.array(rows, dtype=np.float64)
    rec = Recording({"shaft_gyro": Stream("shaft_gyro", "link_gyro", np.arange(len(rows)) * 0.01, values,
                                          ("shaft_gx", "shaft_gy", "shaft_gz"))})
    d = tmp_path_factory.mktemp("rt")
    write_csv(rec, d / "r.csv")
    write_mcap(rec, d / "r.mcap")
    expected = rec.get("shaft_gyro").values  # int64 when every value is whole, else the floats
    for back in (read_csv(d / "r.csv"), read_mcap(d / "r.mcap")[0]):
        got = back.get("shaft_gyro").values
        assert got.dtype == expected.dtype
        np.testing.assert_array_equal(got, expected)
        assert np.array_equal(np.signbit(got), np.signbit(expected)) or expected.dtype == np.int64

"""`armfusion import`: a foreign recording onto an arm's streams, in the units its config
declares, with a bad column map refused clearly, the time stamps a logger got wrong dropped
and said, NaN kept as gaps, and the rig's real slices imported end to end."""

from __future__ import annotations

import json
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import yaml
from armfusion.fusion.cli.main import app
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.importing.column_map import ColumnMapError, load_column_map, parse_column_map
from armfusion.fusion.importing.run import import_recording
from armfusion.fusion.importing.stamps import increasing_rows
from armfusion.fusion.importing.to_stream import ImportMapError, convert_values, targets
from armfusion.sensors.foreign import ForeignFileError
from armfusion.sensors.recording import read_recording, write_recording
from typer.testing import CliRunner

DATA = Path(__file__).resolve().parents[1] / "data"
RIG = DATA / "one_joint_rig.yaml"
runner = CliRunner()


@pytest.fixture(scope="module")
def arm():
    return load_arm(RIG)


def _map(streams: dict, **extra) -> object:
    return parse_column_map({"time": {"column": "t_ms", "unit": "ms"}, "streams": streams, **extra}, "m.yaml")


def _csv(path: Path, rows: list[str], header: str = "t_ms,ax,ay,az,gx,gy,gz,angle_deg") -> Path:
    path.write_text(header + "\n" + "\n".join(rows) + "\n")
    return path


RIG_STREAMS = {
    "shaft": {"columns": ["ax", "ay", "az"], "unit": "g"},
    "imu_gyro": {"columns": ["gx", "gy", "gz"], "unit": "deg/s"},
    "enc": {"columns": ["angle_deg"], "unit": "deg"},
}


# ---------------------------------------------------------------------------- units


def test_g_deg_s_and_deg_become_the_counts_the_config_declares(tmp_path: Path, arm) -> None:
    src = _csv(tmp_path / "log.csv", ["0,0.01,-1.00,0.5,90,0,-45,12.34", "10,0.02,-0.99,0.5,180,1,0,12.33"])
    result = import_recording(src, _map(RIG_STREAMS), arm, str(RIG))
    rec = result.recording
    # the ADXL345 stream is in counts, 256 a g: 0.01 g is 2.56 counts, kept unrounded
    np.testing.assert_allclose(rec.get("shaft").values, [[2.56, -256, 128], [5.12, -253.44, 128]], rtol=1e-12)
    # the MPU-9150 gyro in counts, 131 a deg/s
    np.testing.assert_allclose(rec.get("imu_gyro").values, [[90 * 131, 0, -45 * 131], [180 * 131, 131, 0]],
                               rtol=1e-12)
    # the encoder: 36000 counts a turn, 0.01 deg a count: whole counts, exactly
    assert rec.get("enc").values.dtype == np.int64 and rec.get("enc").values[:, 0].tolist() == [1234, 1233]
    np.testing.assert_array_equal(rec.get("enc").t_s, [0.0, 0.01])  # ms -> s
    assert result.summary["streams"]["enc"]["rounding_max_counts"] < 1e-6


def test_into_streams_declared_in_g_and_rad_s_the_values_convert_by_their_unit_alone(arm) -> None:
    # the rig's config describes its MPU-6050s as delivering g and deg/s; a sensor delivering
    # rad/s is made here from the test config's gyro
    t = targets(load_arm("imu_rig_roll"))
    g_stream = t["shaft"]
    assert (g_stream.value_unit, t["shaft_gyro"].value_unit) == ("g", "deg/s")
    gyro = targets(arm)["imu_gyro"]
    rad_s = replace(gyro, value_unit="rad/s", model=replace(gyro.model, value_unit="rad/s"))
    cmap = _map({"shaft": {"columns": ["a", "b", "c"], "unit": "g"},
                 "imu_gyro": {"columns": ["a", "b", "c"], "unit": "deg/s"}})
    g = np.array([[0.07, 0.82, -0.03]])
    assert convert_values(g, cmap.streams["shaft"], g_stream, "f").values is g  # kept exactly
    mps2 = convert_values(g, replace(cmap.streams["shaft"], unit="m/s^2"), g_stream, "f").values
    np.testing.assert_allclose(mps2, g / 9.80665, rtol=1e-15)
    out = convert_values(np.array([[180.0, -90.0, 0.01]]), cmap.streams["imu_gyro"], rad_s, "f")
    np.testing.assert_allclose(out.values, [[np.pi, -np.pi / 2, np.pi / 18000]], rtol=1e-15)
    back = convert_values(out.values, replace(cmap.streams["imu_gyro"], unit="rad/s"), t["shaft_gyro"], "f")
    np.testing.assert_allclose(back.values, [[180.0, -90.0, 0.01]], rtol=1e-14)  # rad/s into deg/s
    from armfusion.fusion.importing.to_stream import unit_problem

    said = unit_problem("counts", g_stream)
    assert said == ("unit counts cannot become g: the config describes shaft as delivering g, and counts "
                    "need a device's scale")
    assert unit_problem("m/s^2", g_stream) is None


def test_an_encoder_the_config_cannot_hold_in_whole_counts_is_refused_or_rounded_as_allowed(
    tmp_path: Path, arm
) -> None:
    coarse = replace(arm, joints=tuple(replace(j, counts_per_rev=4096.0) for j in arm.joints))
    src = _csv(tmp_path / "log.csv", ["0,0,0,1,0,0,0,0.00", "10,0,0,1,0,0,0,0.05"])
    said = (r"log\.csv: column angle_deg \(deg\) into enc \(enc1\): the config's encoder \(0\.0878906 "
            r"deg a count\) would round the angles by up to 0\.431 counts \(0\.03789 deg, data row 2\), "
            r"more than the map allows \(0\.05 counts\)")
    with pytest.raises(ImportMapError, match=said):
        import_recording(src, _map(RIG_STREAMS), coarse, "coarse")
    loose = {**RIG_STREAMS, "enc": {**RIG_STREAMS["enc"], "max_rounding_counts": 0.5}}
    result = import_recording(src, _map(loose), coarse, "coarse")
    assert result.recording.get("enc").values[:, 0].tolist() == [0, 1]  # 0.05 deg = 0.569 counts
    assert result.summary["streams"]["enc"]["rounding_max_counts"] == pytest.approx(0.431, abs=1e-3)
    assert any("enc: rounded to whole counts by up to 0.431 counts" in c for c in result.changes)


# ---------------------------------------------------------------------------- a bad map


def test_a_map_naming_a_column_the_file_lacks_names_the_column_and_the_file(tmp_path: Path, arm) -> None:
    src = _csv(tmp_path / "log.csv", ["0,0,0,1,0,0,0,0"])
    bad = {**RIG_STREAMS, "shaft": {"columns": ["ax", "ay", "a_z"], "unit": "g"}}
    with pytest.raises(ForeignFileError, match=r"log\.csv: no column 'a_z'; the file has 't_ms', 'ax', 'ay'"):
        import_recording(src, _map(bad), arm, "rig")


def test_a_unit_of_another_quantity_a_missing_stream_and_an_unknown_one_are_said_together(arm) -> None:
    bad = {"shaft": {"columns": ["ax", "ay", "az"], "unit": "deg/s"},
           "wrist_gyro": {"columns": ["gx", "gy", "gz"], "unit": "deg/s"}}
    with pytest.raises(ImportMapError) as caught:
        import_recording("never-read.csv", _map(bad), arm, "rig")
    said = str(caught.value)
    assert "streams.shaft: columns ax, ay, az: unit deg/s (angular_rate) cannot become the stream's counts " \
           "(acceleration, through the sensor model)" in said
    assert ("streams.wrist_gyro: the config rig has no stream 'wrist_gyro'; its streams: shaft, imu_acc"
            in said)
    assert "the config rig needs stream(s) enc, which the map does not give" in said


def test_a_malformed_map_lists_every_problem_with_its_key(tmp_path: Path) -> None:
    p = tmp_path / "m.yaml"
    p.write_text("time: {column: t, unit: kg}\nstart_row: 0\nstreams:\n"
                 "  shaft: {columns: [ax, 'ay[1]'], unit: furlong, scale: 2}\n")
    with pytest.raises(ColumnMapError) as caught:
        load_column_map(p)
    said = str(caught.value)
    assert said.startswith(f"5 problems in column map {p}:")
    for part in ("time.unit: unknown unit 'kg'", "start_row: a row number from 1",
                 "streams.shaft: unknown key(s) scale", "streams.shaft.columns: 'ay[1]' is not a column",
                 "streams.shaft.unit: unknown unit 'furlong'"):
        assert part in said
    ten = ", ".join(["*{}"] * 10)
    p.write_text("a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n" + "".join(
        f"{b}: &{b} [{ten.format(*[a] * 10)}]\n" for a, b in zip("abcde", "bcdef", strict=True)))
    with pytest.raises(ColumnMapError, match=r"aliases expand to more than 200000 values"):
        load_column_map(p)


# ---------------------------------------------------------------------------- stamps and gaps


def test_rows_whose_time_does_not_increase_are_dropped_whole_and_named() -> None:
    t = np.array([0.0, 0.01, 0.01, 0.02, 0.015, 0.03, np.nan, 0.04])
    keep, report = increasing_rows(t, first_row=5)
    assert keep.tolist() == [True, True, False, True, False, True, False, True]
    assert (report.not_increasing, report.not_increasing_rows, report.no_time_rows) == (2, (7, 9), (11,))
    assert report.largest_step_back_s == pytest.approx(0.005)
    assert report.words()[0].startswith("dropped 2 row(s) whose time does not increase, the largest step "
                                        "back 5.000 ms: rows 7 (t = 0.01 s), 9 (t = 0.015 s)")


def test_nan_is_a_gap_of_that_sensor_only_and_repeated_stamps_are_counted(tmp_path: Path, arm) -> None:
    src = _csv(tmp_path / "log.csv", [
        "0,0,0,1,1,2,3,0", "10,NaN,NaN,NaN,1,2,3,0.01", "10,0,0,1,1,2,3,0.02",  # a repeated stamp
        "20,0,,1,1,2,3,0.03", "30,0,0,1,1,2,3,0.04"])
    result = import_recording(src, _map(RIG_STREAMS), arm, "rig")
    rec = result.recording
    np.testing.assert_array_equal(rec.get("shaft").t_s, [0.0, 0.03])
    np.testing.assert_array_equal(rec.get("imu_gyro").t_s, [0.0, 0.01, 0.02, 0.03])
    s = result.summary
    assert s["time"]["not_increasing"] == {"count": 1, "first_rows": [3], "first_t_s": [0.01],
                                           "largest_step_back_s": 0.0}
    assert (s["streams"]["shaft"]["nan_gaps"], s["streams"]["shaft"]["partly_nan"]) == (1, 1)
    assert s["streams"]["imu_gyro"]["nan_gaps"] == 0
    assert "shaft: 1 row(s) NaN in every column and 1 NaN in some of ax, ay, az kept as gaps (not " \
           "sampled), first rows 2, 4" in result.changes


def test_a_row_written_twice_loses_nothing_and_a_sample_with_a_repeated_stamp_exits_1(tmp_path: Path) -> None:
    # a logger writing one row twice: dropped, said, exit 0; two samples stamped alike: the
    # later is dropped, a sample lost: said, the recording written with the rest, exit 1
    twice = _csv(tmp_path / "twice.csv", ["0,0,0,1,1,2,3,0", "10,0,0,1,1,2,3,0.01", "10,0,0,1,1,2,3,0.01",
                                          "20,0,0,1,1,2,3,0.02"])
    alike = _csv(tmp_path / "alike.csv", ["0,0,0,1,1,2,3,0", "10,0,0,1,1,2,3,0.01", "10,0,0,1,1,2,3,0.015",
                                          "20,0,0,1,1,2,3,0.02"])
    cmap = tmp_path / "m.yaml"
    cmap.write_text(yaml.safe_dump({"time": {"column": "t_ms", "unit": "ms"}, "streams": RIG_STREAMS}))
    runs = {}
    for src in (twice, alike):
        out = tmp_path / f"{src.stem}.mcap"
        r = runner.invoke(app, ["import", str(src), "--map", str(cmap), "--config", str(RIG),
                                "--out", str(out), "--json"])
        runs[src.stem] = (r, json.loads(r.stdout), read_recording(out))
    r, s, rec = runs["twice"]
    assert r.exit_code == 0, r.output
    assert s["dropped"] == {"rows": 1, "copies": 1, "lost": 0} and len(rec.get("enc")) == 3
    r, s, rec = runs["alike"]
    assert r.exit_code == 1, r.output
    assert s["dropped"] == {"rows": 1, "copies": 0, "lost": 1} and len(rec.get("enc")) == 3
    assert (f"exit 1: 1 row(s) left out for their time were not copies of the row before (named above): "
            f"samples lost; {tmp_path / 'alike.mcap'} holds the rest") in " ".join(r.stderr.split())


def test_a_file_with_no_row_to_import_is_refused_in_one_line(tmp_path: Path) -> None:
    # before: a header alone was a TypeError traceback after the import had written an empty recording
    cmap = tmp_path / "m.yaml"
    cmap.write_text(yaml.safe_dump({"time": {"column": "t_ms", "unit": "ms"}, "streams": RIG_STREAMS}))
    header_only = _csv(tmp_path / "head.csv", [])
    no_time = _csv(tmp_path / "notime.csv", ["nan,0,0,1,1,2,3,0", ",0,0,1,1,2,3,0"])
    for src, why in ((header_only, "no data row after the header"),
                     (no_time, "none of its 2 data row(s) has a usable time")):
        out = tmp_path / f"{src.stem}.mcap"
        r = runner.invoke(app, ["import", str(src), "--map", str(cmap), "--config", str(RIG),
                                "--out", str(out)])
        assert r.exit_code == 2 and "Traceback" not in r.output, r.output
        assert " ".join(r.stderr.split()) == f"error: cannot import {src}: no row to import: {why}"
        assert not out.exists()


def test_an_infinite_value_is_refused_naming_column_and_row(tmp_path: Path, arm) -> None:
    src = _csv(tmp_path / "log.csv", ["0,0,0,1,1,2,3,0", "10,0,inf,1,1,2,3,0"])
    with pytest.raises(ImportMapError, match=r"log\.csv: column ay: row 2 holds inf, not a value"):
        import_recording(src, _map(RIG_STREAMS), arm, "rig")


def test_an_angle_whose_counts_overflow_is_refused_naming_row_and_columns(tmp_path: Path, arm) -> None:
    # before: 1e308 deg is finite, but inf once in counts: refused by the stream's own check,
    # "raw value inf at sample 1" with no row, column or unit, and numpy's overflow warnings
    src = _csv(tmp_path / "log.csv", ["0,0,0,1,1,2,3,0", "10,0,0,1,1,2,3,1e308", "20,0,0,1,1,2,3,0"])
    with warnings.catch_warnings(record=True) as seen, pytest.raises(ImportMapError) as e:
        warnings.simplefilter("always")
        import_recording(src, _map(RIG_STREAMS), arm, "rig")
    assert str(e.value) == (f"{src}: row 2 (columns angle_deg, stream enc): enc1 = 1e+308 deg is beyond "
                            "any counts a float holds; no sensor the config describes can have said that")
    assert not [w for w in seen if issubclass(w.category, RuntimeWarning)]


# ---------------------------------------------------------------------------- round trips, the real slices


def _rig_map_without_link_gyro(tmp_path: Path) -> Path:
    """The shipped imu-rig map less shaft_gyro, which the one-joint test config (today's
    schema: an ADXL345 on the shaft) cannot hold."""
    m = yaml.safe_load((Path(load_column_map("imu-rig").source)).read_text())
    del m["streams"]["shaft_gyro"]
    p = tmp_path / "rig.yaml"
    p.write_text(yaml.safe_dump(m))
    return p


@pytest.mark.parametrize("suffix", [".mcap", ".csv"])
def test_the_rig_slice_imports_end_to_end_and_reads_back_exactly(tmp_path: Path, suffix: str) -> None:
    src = DATA / "imu-rig" / "raw_roll_slow_20s.mat"
    out = tmp_path / f"roll{suffix}"
    r = runner.invoke(app, ["import", str(src), "--map", str(_rig_map_without_link_gyro(tmp_path)),
                            "--config", str(RIG), "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["rows"] == {"in_file": 2001, "start_row": 2, "before_start": 1, "imported": 1995}
    assert s["time"]["not_increasing"]["count"] == 5  # the logger's 0 ms steps in these 20 s
    raw = scipy.io.loadmat(src)
    t_src = raw["all_time"].ravel()[1:]
    kept = np.concatenate([[True], np.diff(t_src) > 0])
    back = read_recording(out)
    np.testing.assert_array_equal(back.get("enc").t_s, t_src[kept])
    enc_deg = raw["all_encoder"].ravel()[1:][kept]
    np.testing.assert_array_equal(back.get("enc").values[:, 0], np.rint(enc_deg * 100).astype(np.int64))
    np.testing.assert_allclose(back.get("true_q").values[:, 0], np.deg2rad(enc_deg), rtol=1e-9)
    g = np.column_stack([raw[f"all_accel_2_{a}"].ravel()[1:][kept] for a in "xyz"])
    np.testing.assert_allclose(back.get("shaft").values / 256.0, g, rtol=1e-12)
    # what the import made is what the file holds, bit for bit
    made = import_recording(src, load_column_map(_rig_map_without_link_gyro(tmp_path)), load_arm(RIG), "rig")
    for name, stream in made.recording.streams.items():
        assert back.get(name).values.dtype == stream.values.dtype
        if name == "true_q" and suffix == ".csv":  # the CSV holds truth to 10 significant digits
            np.testing.assert_allclose(back.get(name).values, stream.values, rtol=1e-9)
        else:
            np.testing.assert_array_equal(back.get(name).values, stream.values)


def test_the_shipped_rig_map_asks_for_a_link_gyro_a_config_without_one_lacks(tmp_path: Path) -> None:
    r = runner.invoke(app, ["import", str(DATA / "imu-rig" / "raw_yaw_slow_20s.mat"), "--map", "imu-rig",
                            "--config", str(RIG), "--out", str(tmp_path / "yaw.mcap")])
    assert r.exit_code == 2
    assert "streams.shaft_gyro: the config" in r.output and "has no stream 'shaft_gyro'" in r.output
    assert not (tmp_path / "yaw.mcap").exists()


def test_the_broad_slice_imports_with_time_from_its_rate_and_what_it_lacks_said(tmp_path: Path) -> None:
    # BROAD has no arm: the shipped map says why it lacks the encoder, and this one adds the
    # test config's link accelerometer (a config always has one)
    m = yaml.safe_load(Path(load_column_map("broad").source).read_text())
    m["absent"]["shaft"] = "BROAD has no link sensor"
    (tmp_path / "broad.yaml").write_text(yaml.safe_dump(m))
    out = tmp_path / "b.mcap"
    r = runner.invoke(app, ["import", str(DATA / "broad" / "02_undisturbed_slow_rotation_B_3s.hdf5"),
                            "--map", str(tmp_path / "broad.yaml"), "--config", str(RIG), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "enc: absent (BROAD has no arm and no encoder" in r.output
    assert "No change to the source's data" in r.output
    back = read_recording(out)
    import h5py

    with h5py.File(DATA / "broad" / "02_undisturbed_slow_rotation_B_3s.hdf5") as f:
        acc, mag, rate = f["imu_acc"][()], f["imu_mag"][()], f.attrs["sampling_rate"]
    assert len(back.get("imu_acc")) == 857
    np.testing.assert_allclose(back.get("imu_acc").t_s, np.arange(857) / rate, rtol=1e-12)
    np.testing.assert_allclose(back.get("imu_acc").values, acc / 9.80665 * 16384, rtol=1e-12)
    np.testing.assert_allclose(back.get("imu_mag").values, mag / 0.3, rtol=1e-12)  # AK8975: 0.3 uT a count


def test_an_imported_recording_writes_back_through_both_formats_unchanged(tmp_path: Path, arm) -> None:
    rng = np.random.default_rng(18)
    rows = [f"{10 * i},{a:.2f},{b:.2f},{c:.2f},{g:.2f},{h:.2f},{k:.2f},{e:.2f}"
            for i, (a, b, c, g, h, k, e) in enumerate(rng.normal(0, 50, (200, 7))
                                                      * np.array([0.008] * 3 + [1] * 3 + [0.004]))]
    # (within ±2 g; the encoder's steps within what a joint turns in 10 ms)
    made = import_recording(_csv(tmp_path / "log.csv", rows), _map(RIG_STREAMS), arm, "rig").recording
    for suffix in (".mcap", ".csv"):
        write_recording(made, tmp_path / f"r{suffix}")
        back = read_recording(tmp_path / f"r{suffix}")
        for name, s in made.streams.items():
            np.testing.assert_array_equal(back.get(name).values, s.values)
            np.testing.assert_array_equal(back.get(name).t_s, s.t_s)


def test_the_command_refuses_a_bad_map_and_an_unknown_shipped_one_in_one_line(tmp_path: Path) -> None:
    r = runner.invoke(app, ["import", str(DATA / "imu-rig" / "raw_roll_slow_20s.mat"), "--map", "nosuch",
                            "--config", str(RIG), "--out", str(tmp_path / "x.mcap")])
    assert r.exit_code == 2 and "no column map 'nosuch': not a file, and not one of the shipped maps " \
                                "['broad', 'imu-rig', 'ros2-wmra', 'ur5-csv']" in r.output


def test_a_value_beyond_the_configs_sensor_range_is_refused_naming_the_row(tmp_path: Path, arm) -> None:
    # the ADXL345 of the config reads -512 … 511 counts (±2 g at 256 a g): 2.5 g is beyond it,
    # the admission every door applies refuses it (a recording the other commands would refuse)
    src = _csv(tmp_path / "log.csv", ["0,0,0,1,0,0,0,0", "10,2.5,0,1,0,0,0,0", "20,-2.0,0,1,0,0,0,0"])
    with pytest.raises(ValueError, match=r"log\.csv: row 2 \(columns .*stream shaft\): shaft_x = 640 at "
                                         r"t = 0\.01 s is beyond the device's range -512…511"):
        import_recording(src, _map(RIG_STREAMS), arm, "rig")
    # at the limit: a saturated reading, imported and counted
    src = _csv(tmp_path / "ok.csv", ["0,0,0,1,0,0,0,0", "10,1.0,0,1,0,0,0,0", "20,-2.0,0,1,0,0,0,0"])
    s = import_recording(src, _map(RIG_STREAMS), arm, "rig").summary
    assert s["streams"]["shaft"]["at_range_limit"] == 1


@pytest.mark.parametrize("trial, config, before, repeats", [("raw_roll_slow_20s.mat", "imu_rig_roll", 1, 5),
                                                           ("raw_yaw_slow_20s.mat", "imu_rig_yaw", 10, 0)])
def test_the_rig_slices_import_with_the_shipped_map_and_the_rigs_configs_values_kept_as_stored(
    tmp_path: Path, trial: str, config: str, before: int, repeats: int
) -> None:
    src = DATA / "imu-rig" / trial
    out = tmp_path / "rig.mcap"
    r = runner.invoke(app, ["import", str(src), "--map", "imu-rig", "--config", config, "--out", str(out),
                            "--json"])
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["rows"]["before_start"] == before and s["time"]["not_increasing"]["count"] == repeats
    assert s["not_mapped"] == ["imu_temp", "true_base"]
    raw = scipy.io.loadmat(src)
    t_src = raw["all_time"].ravel()[before:]
    kept = np.concatenate([[True], np.diff(t_src) > 0])
    back = read_recording(out)
    # g and deg/s declared by the config: the file's values, bit for bit
    for stream, var in (("shaft", "all_accel_2_"), ("shaft_gyro", "all_gyro_2_"), ("imu_acc", "all_accel_1_"),
                        ("imu_gyro", "all_gyro_1_")):
        expected = np.column_stack([raw[var + a].ravel()[before:][kept] for a in "xyz"])
        np.testing.assert_array_equal(back.get(stream).values, expected)
    assert back.get("shaft_gyro").kind == "link_gyro"
    enc_deg = raw["all_encoder"].ravel()[before:][kept]
    np.testing.assert_array_equal(back.get("enc").values[:, 0], np.rint(enc_deg * 100))  # 36000 a turn

"""The foreign readers: columns of a CSV, a MATLAB .mat and an HDF5 file as float64, only
those named, every refusal naming the file and the column."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io
from armfusion.sensors.foreign import ForeignFileError, parse_address, read_columns
from armfusion.sensors.samples import RecordingError

DATA = Path(__file__).resolve().parents[1] / "data"


def test_an_address_is_a_name_or_a_column_of_a_2d_variable() -> None:
    assert str(parse_address(" imu_acc[ :, 2 ] ")) == "imu_acc[:, 2]"
    assert parse_address("all_time").index is None
    with pytest.raises(ValueError, match=r"'a\[1\]' is not a column: write NAME, or NAME\[:, K\]"):
        parse_address("a[1]")


def test_csv_columns_read_as_floats_with_empty_cells_as_nan(tmp_path: Path) -> None:
    p = tmp_path / "log.csv"
    p.write_text("time_ms,ax,ay,note\n0,0.01,-1,start\n10,,2.5,\n20,NaN,3,x\n")
    cols = read_columns(p, ["time_ms", "ax"])
    assert cols.n_rows == 3 and set(cols.columns) == {"time_ms", "ax"}
    np.testing.assert_array_equal(cols.columns["time_ms"], [0, 10, 20])
    np.testing.assert_array_equal(cols.columns["ax"], [0.01, np.nan, np.nan])


def test_csv_unknown_and_non_numeric_columns_are_named(tmp_path: Path) -> None:
    p = tmp_path / "log.csv"
    p.write_text("time_ms,ax\n0,0.01\n10,abc\n")
    with pytest.raises(ForeignFileError, match=r"log\.csv: no column 'az'; the file has 'time_ms', 'ax'"):
        read_columns(p, ["time_ms", "az"])
    with pytest.raises(RecordingError,
                       match=r"log\.csv: row 2 \(line 3\): column 'ax': 'abc' is not a number"):
        read_columns(p, ["ax"])


def test_mat_column_vectors_and_columns_of_a_matrix(tmp_path: Path) -> None:
    p = tmp_path / "m.mat"
    rng = np.random.default_rng(5)
    acc = rng.normal(size=(40, 3))
    scipy.io.savemat(p, {"t": np.arange(40.0).reshape(-1, 1), "acc": acc, "start": np.array([[3]]),
                         "label": "shaft"})
    cols = read_columns(p, ["t", "acc[:, 2]"], ["start"])
    np.testing.assert_array_equal(cols.columns["acc[:, 2]"], acc[:, 2])
    assert cols.scalars == {"start": 3.0}
    with pytest.raises(ForeignFileError, match=r"m\.mat: column 'acc' is a 40 x 3 array: name one column "
                                               r"of it as acc\[:, K\]"):
        read_columns(p, ["acc"])
    with pytest.raises(ForeignFileError, match=r"m\.mat: column 'label' holds .* values, not numbers"):
        read_columns(p, ["label"])


def test_hdf5_columns_their_bounds_and_a_file_attribute(tmp_path: Path) -> None:
    p = tmp_path / "b.hdf5"
    with h5py.File(p, "w") as f:
        f["imu_acc"] = np.arange(30.0).reshape(10, 3)
        f["short"] = np.arange(9.0)
        f.attrs["sampling_rate"] = 285.7
    cols = read_columns(p, ["imu_acc[:, 1]"], ["sampling_rate"])
    np.testing.assert_array_equal(cols.columns["imu_acc[:, 1]"], np.arange(1.0, 30.0, 3))
    assert cols.scalars["sampling_rate"] == 285.7
    with pytest.raises(ForeignFileError, match=r"b\.hdf5: column 'imu_acc\[:, 3\]': the variable has 3 "
                                               r"columns \(K from 0 to 2\)"):
        read_columns(p, ["imu_acc[:, 3]"])
    with pytest.raises(ForeignFileError, match=r"column 'short' has 9 rows but 'imu_acc\[:, 0\]' has 10"):
        read_columns(p, ["imu_acc[:, 0]", "short"])


def test_a_file_of_another_kind_or_suffix_is_refused_by_name(tmp_path: Path) -> None:
    (tmp_path / "x.mat").write_text("not a mat file at all")
    with pytest.raises(ForeignFileError, match=r"x\.mat: not a MATLAB \.mat file"):
        read_columns(tmp_path / "x.mat", ["t"])
    (tmp_path / "x.h5").write_text("nor HDF5")
    with pytest.raises(ForeignFileError, match=r"x\.h5: not an HDF5 file"):
        read_columns(tmp_path / "x.h5", ["t"])
    with pytest.raises(ForeignFileError, match=r"unknown suffix '\.xlsx'; the import reads \.csv"):
        read_columns(tmp_path / "x.xlsx", ["t"])


def test_a_fifo_a_directory_and_a_device_are_refused_as_not_a_file_at_once(tmp_path: Path) -> None:
    # before: a FIFO or a directory was "no such file" (it is there), a FIFO as a bag
    # "[Errno 20] Not a directory"
    import os

    from armfusion.sensors.foreign.rosbag import read_topics

    os.mkfifo(tmp_path / "pipe.csv")
    os.mkfifo(tmp_path / "pipe.mcap")
    (tmp_path / "dir.csv").mkdir()
    for p in (tmp_path / "pipe.csv", tmp_path / "dir.csv"):
        with pytest.raises(ForeignFileError, match=r"not a regular file \(a device, a FIFO, a directory\)"):
            read_columns(p, ["t"])
    with pytest.raises(ForeignFileError, match=r"pipe\.mcap: not a regular file or a bag directory"):
        read_topics(tmp_path / "pipe.mcap", {"/a": ["x"]})
    with pytest.raises(ForeignFileError, match=r"x\.csv: no such file"):
        read_columns(tmp_path / "x.csv", ["t"])


def test_the_shipped_rig_slice_holds_what_its_readme_says() -> None:
    cols = read_columns(DATA / "imu-rig" / "raw_roll_slow_20s.mat", ["all_time", "all_encoder"],
                        ["data_line"])
    assert cols.n_rows == 2001 and cols.scalars["data_line"] == 2.0
    assert cols.columns["all_time"][0] == pytest.approx(12.109)


def test_a_dataset_claiming_more_values_than_the_import_takes_is_refused_unread(tmp_path: Path) -> None:
    p = tmp_path / "huge.h5"
    with h5py.File(p, "w") as f:  # 2^29 values declared, nothing written: a few kB on disk
        f.create_dataset("acc", shape=(1 << 27, 4), dtype="f8", chunks=(1024, 4))
    assert p.stat().st_size < 100_000
    with pytest.raises(ForeignFileError, match=r"huge\.h5: column 'acc\[:, 0\]': its variable holds "
                                               r"536870912 values; the import takes at most 268435456"):
        read_columns(p, ["acc[:, 0]"])

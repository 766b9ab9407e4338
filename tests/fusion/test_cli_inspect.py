"""`armfusion inspect` on a CSV written by another program, following the spec."""

from __future__ import annotations

import csv
import json

import numpy as np
from armfusion.fusion.cli.main import app
from typer.testing import CliRunner

runner = CliRunner()


def _foreign_csv(path, rng):
    """A logger of someone else's: its own column order, an extra column, the IMU at 200 Hz
    and the accelerometers at 100 Hz (empty cells between), a still stretch, then motion."""
    t = np.round(np.arange(0, 20, 0.005), 6)  # 200 Hz instants
    rows = []
    for i, ti in enumerate(t):
        moving = 8.0 <= ti < 12.0
        wobble = 40 * np.sin(2 * np.pi * 0.7 * ti) if moving else 0.0
        row = {"t": f"{ti:.3f}", "logger_cpu_temp": "41.5",
               "imu_ax": int(rng.normal(0, 40)), "imu_ay": int(rng.normal(0, 40)),
               "imu_az": int(16384 + rng.normal(0, 40)),
               "imu_gx": int(rng.normal(0, 4) + (300 if moving else 0)),
               "imu_gy": int(rng.normal(0, 4)), "imu_gz": int(rng.normal(0, 4))}
        if i % 2 == 0:  # 100 Hz
            for a, base in (("acc1", (0, 0, 256)), ("acc2", (181, 0, 181))):
                for k, ax in enumerate("xyz"):
                    row[f"{a}_{ax}"] = int(round(base[k] + wobble + rng.normal(0, 0.8)))
            for j in range(1, 8):
                row[f"enc{j}"] = int(1000 * j + (ti - 8) * 5000 * moving)
        else:
            for a in ("acc1", "acc2"):
                for ax in "xyz":
                    row[f"{a}_{ax}"] = ""
            for j in range(1, 8):
                row[f"enc{j}"] = ""
        rows.append(row)
    cols = ["imu_az", "t", "acc2_z", "acc2_y", "acc2_x", "logger_cpu_temp", "imu_ax", "imu_ay",
            "acc1_x", "acc1_y", "acc1_z", "imu_gx", "imu_gy", "imu_gz"] + [f"enc{j}" for j in range(1, 8)]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols, lineterminator="\r\n")
        w.writeheader()
        w.writerows(rows)


def test_inspect_reports_sensors_rates_and_still_segments(tmp_path, rng):
    p = tmp_path / "foreign.csv"
    _foreign_csv(p, rng)
    r = runner.invoke(app, ["inspect", str(p), "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    streams = {s["name"]: s for s in d["streams"]}
    assert set(streams) == {"acc1", "acc2", "imu_acc", "imu_gyro", "enc"}
    assert abs(streams["acc1"]["rate_hz"] - 100) < 0.5 and streams["acc1"]["samples"] == 2000
    assert abs(streams["imu_acc"]["rate_hz"] - 200) < 0.5 and streams["imu_acc"]["samples"] == 4000
    assert streams["enc"]["channels"] == [f"enc{j}" for j in range(1, 8)]
    assert abs(d["duration_s"] - 19.995) < 1e-6
    segs = d["static_segments"]
    assert len(segs) == 2
    assert segs[0]["t_start_s"] < 0.2 and 7.0 < segs[0]["t_end_s"] <= 8.3
    assert 11.5 <= segs[1]["t_start_s"] < 13.0 and segs[1]["t_end_s"] > 19.8
    # the human view says the same, and warns once about the unknown column
    r2 = runner.invoke(app, ["inspect", str(p)])
    assert r2.exit_code == 0
    assert "imu_gyro" in r2.stdout and "Still segments (2)" in r2.stdout
    assert r2.stderr.count("logger_cpu_temp") == 1


def test_inspect_names_the_bad_row(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("t,acc1_x,acc1_y,acc1_z\n0.0,1,2,256\n0.01,1,2,256\n0.005,1,2,256\n")
    r = runner.invoke(app, ["inspect", str(p)])
    assert r.exit_code == 2
    assert "bad.csv" in r.stderr and "row 3" in r.stderr

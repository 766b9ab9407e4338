"""The demo's HTML report says what gravity reads together (name, value, σ), as the track
JSON and CSV do, scored against the same combination of the truth."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.cli.demo_report import score_combinations, write_report
from armfusion.sensors.samples import TRUTH_BASE_COLUMNS, Stream


def _ev(tmp_path):
    names = ["j1", "j2", "j3"]
    t = np.linspace(0.0, 4.0, 41)
    q_true = np.column_stack([0.1 * t, 0.3 + 0.0 * t, -0.2 + 0.05 * t])
    tilt = np.column_stack([np.full_like(t, 0.01), np.full_like(t, -0.02)])
    # the estimates: j2 + j3 and j3 - base pitch reported from the second half, off by 0.5°
    # and 4° at a sigma of 1° each (the second outside its 3 sigma)
    off = np.radians([0.5, 4.0])
    reported = [None if k < 20 else (
        {"name": "j2 + j3", "coefficients": {"j2": 1.0, "j3": 1.0},
         "angle_rad": float(q_true[k, 1] + q_true[k, 2] + off[0]), "sigma_rad": float(np.radians(1.0))},
        {"name": "j3 - base pitch", "coefficients": {"j3": 1.0, "base pitch": -1.0},
         "angle_rad": float(q_true[k, 2] - tilt[k, 1] + off[1]), "sigma_rad": float(np.radians(1.0))})
        for k in range(len(t))]
    combos = score_combinations(reported, t, q_true, tilt, names)
    tq = Stream("true_q", "truth_q", t, q_true, tuple(names))
    tb = Stream("true_base", "truth_base", t, np.column_stack([tilt, 0.0 * t]), TRUTH_BASE_COLUMNS)
    ev = {"joint_names": names,
          "startup": {"t_s": 0.0, "message": "ok",
                      "joints": {n: {"error_deg": 0.0, "sigma_deg": 1.0, "flag": "ok"} for n in names}},
          "tracking": {"t_start_s": 0.0, "t_end_s": 4.0, "estimates": len(t),
                       "rms_error_deg": dict.fromkeys(names, 0.0), "max_error_deg": dict.fromkeys(names, 0.0),
                       "within_3_sigma": dict.fromkeys(names, 1.0), "from_first_ok": dict.fromkeys(names),
                       "heading_rms_deg": None, "heading_within_3_sigma": None, "heading_status": {},
                       "combinations": combos},
          "flags_seen": {n: {"ok": len(t)} for n in names},
          "samples": {"published": 1, "received_by_serve": 1, "recorded": 1, "dropped": {}},
          "latency": None,
          "_series": {"t": t, "q": q_true, "sigma": np.full_like(q_true, 0.01), "flags": None,
                      "truth_q": tq, "truth_base": tb, "headings": []}}
    return ev, combos


def test_the_combinations_are_scored_against_the_truth_over_the_estimates_they_were_reported_at(tmp_path):
    _, combos = _ev(tmp_path)
    by = {c["name"]: c for c in combos}
    assert set(by) == {"j2 + j3", "j3 - base pitch"}
    a, b = by["j2 + j3"], by["j3 - base pitch"]
    assert abs(a["rms_error_deg"] - 0.5) < 1e-9 and a["within_3_sigma"] == 1.0
    assert abs(b["rms_error_deg"] - 4.0) < 1e-9 and b["within_3_sigma"] == 0.0
    assert abs(a["reported_share"] - 21 / 41) < 1e-12 and abs(a["sigma_deg"] - 1.0) < 1e-9
    assert abs(a["angle_deg"] - np.degrees(0.3 + (-0.2 + 0.2) + np.radians(0.5))) < 1e-9


def test_the_html_report_lists_each_combination_with_its_value_and_sigma(tmp_path):
    ev, combos = _ev(tmp_path)
    doc = {"realistic": False, "seed": 0, "scenario": "s", "duration_s": 4.0, "config": "c"}
    text = write_report(tmp_path / "report.html", doc, ev, None, None).read_text(encoding="utf-8")
    assert "What gravity reads together" in text
    for c in combos:
        row = text[text.index(f"<td>{c['name']}</td>"):]
        row = row[:row.index("</tr>")]
        assert f"{c['angle_deg']:+.2f}" in row and f"{c['sigma_deg']:.2f}" in row
        assert f"{c['rms_error_deg']:.2f}" in row
    ev["tracking"]["combinations"] = []
    text = write_report(tmp_path / "none.html", doc, ev, None, None).read_text(encoding="utf-8")
    assert "no combination" in text

"""A parameter whose fit ends at its bound is never written: end to end, through the command."""

import json

import numpy as np
import yaml
from armfusion.fusion.cli.main import app
from armfusion.fusion.configfile import load_arm
from armfusion.models.effects import build_effect
from typer.testing import CliRunner


def test_an_estimate_at_its_bound_is_written_at_its_prior_and_said(tmp_path):
    """acc2 reads 15 % low on every axis, the scale's bound: `--add accel_scale:acc2 --write`
    fits it there, and the config written carries the scale at its prior (0, with the prior σ
    and no covariance with anything else), each element named in a comment and in
    ``at_bound``; what is judged on the held-out part is that config, not the fit at the
    bound."""
    runner = CliRunner()
    rec = tmp_path / "low.csv"
    r = runner.invoke(app, ["simulate", "--scenario", "renk-maneuver", "--duration", "20", "--seed", "5",
                            "--effect", "accel_scale:acc2=-0.15,-0.15,-0.15", "--out", str(rec)])
    assert r.exit_code == 0, r.output
    out = tmp_path / "w.yaml"
    r = runner.invoke(app, ["diagnose", str(rec), "--config", "wmra", "--add", "accel_scale:acc2",
                            "--write", str(out), "--json", "--history", str(tmp_path / "h.json")])
    doc = json.loads(r.stdout)
    names = [f"acc2.accel_scale[{a}]" for a in "xyz"]
    assert sorted(doc["at_bound"]) == names
    assert doc["written_held_out_rms_ratio"] is not None
    # the fit at the bound explains the held-out part; what is written (the prior) does not
    assert doc["held_out"]["rms_ratio"] < doc["written_held_out_rms_ratio"]
    # the prior is what the replaced config had: no worse on the held-out part, so written
    assert r.exit_code == 0 and doc["write_refused"] is None, r.output
    text = out.read_text(encoding="utf-8")
    for n in names:
        assert f"# {n}: its fit ended at the parameter's bound; written at its prior" in text
    cfg = yaml.safe_load(text)
    scale = [e for e in cfg["effects"] if e["effect"] == "accel_scale" and e["target"] == "acc2"]
    assert len(scale) == 1
    (values,) = scale[0]["params"].values()
    assert np.allclose(values, 0.0)
    cov = cfg["calibration"]["correction_covariance"]["acc2"]
    idx = [cov["elements"].index(n) for n in names]
    C = np.array(cov["matrix"])
    prior_sigma = build_effect(load_arm("wmra"), "accel_scale", "acc2").default_sigma()
    assert np.allclose(np.sqrt(np.diag(C)[idx]), prior_sigma)  # the library's prior σ, not the fit's
    off = C[np.ix_(idx, [i for i in range(len(C)) if i not in idx])]
    assert np.all(off == 0.0)

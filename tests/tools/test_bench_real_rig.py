"""The real-rig bench runs every trial of a folder to the end: a trial that cannot be read
(or any stage of one that fails) is a row of its table saying what failed, and the bench
goes on to the next trial."""

from __future__ import annotations

import numpy as np
import scipy.io

from tools.bench_real_rig import STAGES, TrialResult, benchmarks_section, real_data_doc, run_trial


def test_a_trial_that_fails_is_a_row_of_the_table_not_the_end_of_the_bench(tmp_path, capsys):
    (tmp_path / "a_broken.mat").write_text("not a MATLAB file", encoding="utf-8")
    scipy.io.savemat(tmp_path / "b_no_columns.mat", {"something_else": np.zeros((10, 1))})
    from tools.bench_real_rig import main

    assert main(["--data", str(tmp_path), "--no-write"]) == 0
    out = capsys.readouterr().out
    for name in ("a_broken", "b_no_columns"):  # both trials reached, each with its failure
        row = next(line for line in out.splitlines() if line.startswith(f"| {name} |"))
        assert "**import failed**" in row
    assert "Trials that did not reach a set-up (every target missed): a_broken, b_no_columns." in out


def test_the_stages_after_a_failed_one_say_they_were_not_run(tmp_path):
    (tmp_path / "broken.mat").write_text("not a MATLAB file", encoding="utf-8")
    r = run_trial(tmp_path / "broken.mat", 300.0, 2, tmp_path)
    assert isinstance(r, TrialResult) and r.rungs is None and r.track is None
    assert r.failed("import").startswith("ForeignFileError")
    assert all(r.failed(s) == "not run (import failed)" for s in STAGES[1:])
    doc = real_data_doc([r], 300.0)
    assert "## broken" in doc and "- import: ForeignFileError" in doc
    assert "| broken | **import failed**" in benchmarks_section([r], 300.0)


def test_trials_run_side_by_side_come_back_in_the_folders_order(tmp_path, capsys):
    for name in ("c_third", "a_first", "b_second"):
        (tmp_path / f"{name}.mat").write_text("not a MATLAB file", encoding="utf-8")
    from tools.bench_real_rig import main

    assert main(["--data", str(tmp_path), "--no-write", "--jobs", "2"]) == 0
    rows = [line.split(" |")[0] for line in capsys.readouterr().out.splitlines()
            if line.startswith("| ") and "**import failed**" in line]
    assert rows == ["| a_first", "| b_second", "| c_third"]

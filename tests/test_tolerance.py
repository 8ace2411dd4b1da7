"""Success against the tolerance (evaluation/tolerance.py): the same trials judged at every tolerance."""
from __future__ import annotations

import json

import numpy as np
from PIL import Image

from evaluation.tolerance import curves, main, within


def record(obj: str, error_m: float | None, turned: float | None, outcome: str = "failure", **extra) -> dict:
    return {"object_id": obj, "method": "m", "outcome": outcome, "success": False, "position_error_m": error_m,
            "rotation_deg": turned, "toppled": False, **extra}


RECORDS = [record("a", 0.005, 5.0), record("a", 0.015, 12.0), record("b", 0.025, 40.0), record("b", 0.045, 3.0),
           record("b", None, None, outcome="error")]


def test_a_trial_succeeds_within_a_tolerance_only_if_it_ended_inside_it_upright():
    assert within(RECORDS[1], 0.02, 15.0) and not within(RECORDS[1], 0.01, 15.0) and not within(RECORDS[1], 0.02, 10.0)
    assert not within(record("a", 0.001, 1.0, toppled=True), 0.05, 45.0)  # over: no tolerance saves it
    assert not within(RECORDS[4], 1.0, 180.0)  # an error has no final pose


def test_curves_count_the_same_trials_at_each_tolerance():
    c = curves(RECORDS)
    assert c.trials == 5
    # within 1..5 cm at <= 45 degrees: 1, 2, 3, 3, 4 of 5
    assert [round(i.value * 5) for i in c.by_position] == [1, 2, 3, 3, 4]
    # within 3 cm at <= 10, 15, 20, 30, 45 degrees: 1, 2, 2, 2, 3 of 5
    assert [round(i.value * 5) for i in c.by_rotation] == [1, 2, 2, 2, 3]
    assert all(i.low <= i.value <= i.high for i in (*c.by_position, *c.by_rotation))


def test_the_command_writes_a_table_and_a_plot_and_refuses_a_directory_that_is_not_a_run(tmp_path, capsys):
    run = tmp_path / "closed-loop-real"
    run.mkdir()
    (run / "records.jsonl").write_text("".join(json.dumps({**r, "key": f"k{i}"}) + "\n" for i, r in enumerate(RECORDS)))
    assert main([str(run), "--out", str(tmp_path / "tolerance.md")]) == 0
    text = (tmp_path / "tolerance.md").read_text()
    assert "| closed-loop-real / m | 5 | 20% [" in text and "![success against the tolerance](tolerance.png)" in text
    with Image.open(tmp_path / "tolerance.png") as image:
        assert image.size[0] > 600 and np.asarray(image.convert("L")).std() > 10
    assert main([str(tmp_path / "nothing")]) == 2
    assert "not a `gd2p eval` run" in capsys.readouterr().err


def test_a_pose_goal_is_read_by_its_yaw_miss_and_a_rolling_object_by_its_position():
    from evaluation.tolerance import within

    pose = {"outcome": "success", "position_error_m": 0.015, "rotation_deg": 38.0, "yaw_error_deg": 6.0}
    assert within(pose, 0.02, 10.0) and not within(pose, 0.02, 5.0)  # turned 38 degrees as asked: 6 off the goal
    rolled = {"outcome": "failure", "position_error_m": 0.02, "rotation_deg": 170.0, "toppled": True, "shape": "round"}
    assert within(rolled, 0.03, 10.0) and not within(rolled, 0.01, 45.0)

"""The engine comparison report (`python -m evaluation.engines`): trials matched by request, why trials failed,
the tracker's error."""
from __future__ import annotations

import json

from evaluation.engines import failure_cause, main, report


def _record(method: str, object_id: str, trial: int, success: bool, engine: str, **extra) -> dict:
    key = f"{method}/allegro/{object_id}/60/{trial}"
    return {"key": key, "method": method, "hand": "allegro", "object_id": object_id, "direction_deg": 60.0,
            "trial": trial, "seed": 7 + trial, "success": success, "outcome": "success" if success else "failure",
            "engine": engine, "code": "abc1234",
            "tracker": {"mode": "image", "pushes": [{"frames": 10, "lost": 1, "median_mm": 4.0 + trial,
                                                     "worst_mm": 9.0, "median_deg": 1.0, "worst_deg": 3.0}]},
            **extra}


def _write(directory, records):
    directory.mkdir()
    (directory / "records.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def test_a_failed_trial_is_put_down_to_what_failed():
    assert failure_cause({"success": True}) is None
    assert failure_cause({"success": False, "error_code": "bad_request"}) == "perception"
    assert failure_cause({"success": False, "error_code": "infeasible"}) == "planning"
    assert failure_cause({"success": False, "error_code": "lost"}) == "tracking"
    assert failure_cause({"success": False, "outcome": "failure",
                          "notes": ["push 1 stopped: 0.3 s into the push the tracker lost the object (x)"]}) == "tracking"
    assert failure_cause({"success": False, "outcome": "failure"}) == "push"


def test_the_report_pairs_the_same_requests_and_counts_causes(tmp_path):
    real = [_record("m", obj, t, True, "pybullet") for obj in ("a", "b") for t in range(2)]
    mujoco = [_record("m", "a", 0, True, "mujoco"), _record("m", "a", 1, False, "mujoco", error_code="lost"),
              _record("m", "b", 0, False, "mujoco"), _record("m", "b", 1, True, "mujoco"),
              _record("m", "c", 0, True, "mujoco")]  # not in the real run: left out
    _write(tmp_path / "real", real)
    _write(tmp_path / "mujoco", mujoco)
    text = report(tmp_path / "real", tmp_path / "mujoco")
    assert "| m | 4 | 2 | 100.0%" in text and "50.0%" in text
    assert "| m | MuJoCo | 0 | 0 | 1 | 1 | 0 |" in text
    assert "10.0%" in text  # frames lost: 1 in 10 per push
    assert main([str(tmp_path / "real"), str(tmp_path / "nowhere")]) == 2


def test_the_report_gives_the_default_minus_each_baseline_in_each_engine(tmp_path):
    default, baseline = "gd2p-closed-critic-p24", "fixed-corrected"
    real = ([_record(default, o, t, True, "pybullet") for o in ("a", "b") for t in range(2)]
            + [_record(baseline, o, t, t == 0, "pybullet") for o in ("a", "b") for t in range(2)])
    mujoco = ([_record(default, o, t, o == "a", "mujoco") for o in ("a", "b") for t in range(2)]
              + [_record(baseline, o, t, False, "mujoco") for o in ("a", "b") for t in range(2)])
    _write(tmp_path / "real", real)
    _write(tmp_path / "mujoco", mujoco)
    text = report(tmp_path / "real", tmp_path / "mujoco")
    assert "## The default (gd2p-closed-critic-p24) minus each method, in each engine" in text
    row = next(line for line in text.splitlines() if line.startswith(f"| {baseline} | 4 | +"))
    assert row.startswith(f"| {baseline} | 4 | +50.0 [") and row.split("|")[4].strip().startswith("+50.0 [")  # 100-50, 50-0


def test_the_report_can_leave_out_a_method_still_running(tmp_path):
    real = [_record(m, "a", 0, True, "pybullet") for m in ("m", "running")]
    mujoco = [_record(m, "a", 0, True, "mujoco") for m in ("m", "running")]
    _write(tmp_path / "real", real)
    _write(tmp_path / "mujoco", mujoco)
    text = report(tmp_path / "real", tmp_path / "mujoco", only=["m"])
    assert "| m |" in text and "| running |" not in text
    assert main([str(tmp_path / "real"), str(tmp_path / "mujoco"), "--methods", "nothing"]) == 2

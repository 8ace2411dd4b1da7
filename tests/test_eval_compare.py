"""`gd2p compare`: two runs of one protocol, matched trial by trial (evaluation/compare.py)."""
from __future__ import annotations

import json

import pytest

from cli.main import main
from evaluation.compare import CompareError, compare, load_run


def _record(obj: str, trial: int, success: bool, method: str = "gd2p", draw_seed: int | None = None, **extra) -> dict:
    return {"key": f"{method}/allegro/{obj}/60/{trial}", "method": method, "hand": "allegro", "object_id": obj,
            "direction_deg": 60.0, "trial": trial, "seed": 100 + trial, "world": "real",
            "world_draw": {"seed": draw_seed if draw_seed is not None else 200 + trial}, "success": success, **extra}


def _run(directory, records):
    directory.mkdir()
    (directory / "records.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records) + '{"torn": ')
    return directory


def test_runs_are_compared_on_the_trials_that_are_the_same_episode(tmp_path):
    a = _run(tmp_path / "a", [_record(o, t, o == "box") for o in ("box", "mug") for t in range(3)]
             + [_record("box", 0, False, method="fixed")])
    b = _run(tmp_path / "b", [_record(o, t, True, pose_model="allegro:v2") for o in ("box", "mug") for t in range(5)]
             + [_record("cone", 0, True)])
    report = compare(load_run(a, "gd2p"), load_run(b, "gd2p"))
    assert "6 trials are the same episode in both runs (2 objects; of 6 and 11 trials)" in report
    assert "| a:gd2p | 6 | 50.0%" in report and "| b:gd2p | 6 | 100.0%" in report and "allegro:v2 (6)" in report
    assert "B − A, paired by object: +50.0" in report
    assert "| 3 | 0 | 3 | 0 |" in report  # both succeed, only A, only B, both fail


def test_another_world_draw_is_another_episode_and_bad_runs_are_refused(tmp_path, capsys):
    a = _run(tmp_path / "a", [_record("box", 0, True)])
    b = _run(tmp_path / "b", [_record("box", 0, True, draw_seed=999)])
    with pytest.raises(CompareError, match="share no episode"):
        compare(load_run(a, "gd2p"), load_run(b, "gd2p"))
    with pytest.raises(CompareError, match="no trials of method 'nearest'; it has: gd2p"):
        load_run(a, "nearest")
    assert main(["compare", str(tmp_path / "missing"), str(b)]) == 2
    assert "no records.jsonl" in capsys.readouterr().err
    out = tmp_path / "cmp.md"
    assert main(["compare", f"{a}:gd2p", str(a), "--out", str(out)]) == 0
    assert "+0.0" in out.read_text()


def test_across_worlds_the_same_request_is_paired_whatever_world_executed_it(tmp_path):
    exact = _run(tmp_path / "methods-exact-v2", [{**_record(o, t, True), "world": "exact", "world_draw": {"seed": 7}}
                                                 for o in ("box", "mug") for t in range(2)])
    real = _run(tmp_path / "methods-real-v2", [_record(o, t, o == "box" or t == 0) for o in ("box", "mug")
                                               for t in range(2)] + [_record("box", 0, True, method="fixed")])
    with pytest.raises(CompareError, match="share no episode"):
        compare(load_run(exact, "gd2p"), load_run(real, "gd2p"))
    report = compare(load_run(exact, "gd2p"), load_run(real, "gd2p"), across_worlds=True)
    assert "4 trials are the same request, each executed in its run's world, in both runs (2 objects" in report
    assert "| methods-exact-v2:gd2p | 4 | 100.0%" in report and "| exact (4) |" in report and "| real (4) |" in report
    assert "B − A, paired by object: -25.0" in report and "| 3 | 1 | 0 | 0 |" in report
    out = tmp_path / "cmp.md"
    assert main(["compare", f"{exact}:gd2p", str(real), "--across-worlds", "--out", str(out)]) == 0
    assert "-25.0" in out.read_text() and "- command: `" in out.read_text()


def _coverage_record(source: str, obj: str, successes: int, world_seed: int = 1, pushed: int = 10) -> dict:
    return {"key": f"{source}/{obj}", "object": obj, "fraction_pushed": pushed, "fraction_successes": successes,
            "code": "abc", "world": {"level": "real", "cameras": 3, "seed": world_seed}}


def test_sampler_quality_runs_pair_a_source_object_by_object_in_the_same_drawn_world(tmp_path, capsys):
    """The same source under two critics: objects pair only when measured in the same world, each pose a trial."""
    a = _run(tmp_path / "sq-mesh-critic", [_coverage_record("ddpm100-critic", "box", 5), _coverage_record("ddpm100-critic", "mug", 8),
                                           _coverage_record("nn", "box", 9), _coverage_record("ddpm100-critic", "cone", 1)])
    b = _run(tmp_path / "sq-capture-critic", [_coverage_record("ddpm100-critic", "box", 9), _coverage_record("ddpm100-critic", "mug", 8),
                                              _coverage_record("ddpm100-critic", "cone", 10, world_seed=2)])
    report = compare(load_run(a, "ddpm100-critic"), load_run(b, "ddpm100-critic"))
    assert "2 objects are the same object in the same drawn world in both runs (of 3 and 3)" in report
    assert "| sq-mesh-critic:ddpm100-critic | 2 | 65.0%" in report and "| sq-capture-critic:ddpm100-critic | 2 | 85.0%" in report
    assert "B − A, paired by object: +20.0" in report and "| 1 | 0 | 1 |" in report and "real, 3 cameras (2)" in report
    assert "3 objects are the same object in both runs" in compare(load_run(a, "ddpm100-critic"),
                                                                   load_run(b, "ddpm100-critic"), across_worlds=True)
    with pytest.raises(CompareError, match="no trials of method 'gd2p'; it has: ddpm100-critic, nn"):
        load_run(a, "gd2p")
    trials = _run(tmp_path / "methods", [_record("box", 0, True)])
    with pytest.raises(CompareError, match="compares only with another"):
        compare(load_run(trials, "gd2p"), load_run(b, "ddpm100-critic"))
    assert main(["compare", f"{a}:nn", f"{b}:ddpm100-critic"]) == 0
    assert "B − A, paired by object: +0.0" in capsys.readouterr().out  # box: 9 of 10 each

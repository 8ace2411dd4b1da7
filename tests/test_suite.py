"""The task families and `gd2p eval suite`: what a pose trial asks and how it is judged, and the suite's report."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from evaluation import push_protocol as protocol
from evaluation.tasks import POSE_TASK_TURN_DEG
from shared.frames import direction_xy, make_transform, yaw_rotation
from shared.world.push_outcome import object_pose

ROOT = Path(__file__).resolve().parents[1]


def pose_episode(trial: int = 0, **kwargs) -> protocol.Episode:
    return protocol.Episode("gd2p-closed-critic-p24", "allegro", "proc-box-001", 60.0, trial, task="pose", **kwargs)


def test_every_task_meets_the_same_trials_under_keys_of_its_own():
    paper = protocol.Episode("gd2p-closed-critic-p24", "allegro", "proc-box-001", 60.0, 0)
    pose = pose_episode()
    assert paper.key == "gd2p-closed-critic-p24/allegro/proc-box-001/60/0"  # the paper's runs keep their records
    assert pose.key == "pose:" + paper.key
    assert (pose.seed, pose.world_seed) == (paper.seed, paper.world_seed)
    assert pose.goal_turn_deg == POSE_TASK_TURN_DEG and pose_episode(1).goal_turn_deg == -POSE_TASK_TURN_DEG
    with pytest.raises(ValueError, match="unknown task"):
        protocol.episodes(["gd2p"], "allegro", ["proc-box-001"], [60.0], 1, task="stack")


def test_the_pose_task_leaves_out_objects_without_a_yaw():
    objects = protocol.task_objects("pose", protocol.PROCEDURAL_OBJECTS + protocol.EVERYDAY_OBJECTS)
    assert "proc-box-001" in objects and "pb-mug" in objects
    assert not {"proc-cylinder-000", "proc-cylinder-001", "proc-cone-000"} & set(objects)  # bodies of revolution
    assert protocol.task_objects("paper", ["proc-cone-000"]) == ("proc-cone-000",)


def test_a_pose_trial_asks_for_the_point_and_a_turn_from_the_yaw_the_system_sees():
    episode = pose_episode()
    T_start = protocol.put_down(episode, protocol.execution_world(episode))
    request = protocol.push_request(episode, T_start)  # told the mesh at the told placement
    assert request.direction_deg is None
    np.testing.assert_allclose(request.goal_xy, T_start[:2, 3] + 0.20 * direction_xy(60.0))
    told = protocol.placement(episode)
    told_yaw = math.degrees(math.atan2(told[1, 0], told[0, 0]))  # the box stands as modelled: the yaw of its frame
    assert request.goal_yaw_deg == pytest.approx(told_yaw + POSE_TASK_TURN_DEG, abs=1e-6)


def test_a_shape_task_asks_the_papers_push():
    episode = protocol.Episode("gd2p-closed-critic-p24", "allegro", "proc-lying-000", 60.0, 0, task="round")
    request = protocol.push_request(episode, protocol.placement(episode))
    assert (request.direction_deg, request.goal_xy, request.goal_yaw_deg) == (60.0, None, None)


def test_a_pose_trial_is_judged_by_where_and_how_turned_the_object_truly_ended():
    episode = pose_episode(trial=1)  # a clockwise turn
    T_start = protocol.put_down(episode, protocol.execution_world(episode))
    target = T_start[:2, 3] + 0.20 * direction_xy(60.0)

    def ended(turn_deg: float, off_m: float = 0.0) -> dict:
        T = make_transform(yaw_rotation(math.radians(turn_deg)) @ T_start[:3, :3],
                           np.array([target[0] + off_m, target[1], T_start[2, 3]]))
        return protocol.judged_from(episode, T_start, object_pose(T))

    assert ended(-30.0).success and ended(-20.0).success
    assert not ended(0.0).success and not ended(+30.0).success  # not turned, or turned the wrong way
    assert not ended(-30.0, off_m=0.025).success  # 2.5 cm off: a pose goal's 2 cm
    assert ended(-30.0).yaw_error_deg == pytest.approx(0.0, abs=1e-6)


def fake_trial(episode: protocol.Episode) -> dict:
    """A trial's record without the physics: the default succeeds every time, the fixed pose on trial 0 only."""
    success = episode.method == "gd2p-closed-critic-p24" or episode.trial == 0
    return {**asdict(episode), "seed": episode.seed, "outcome": "success" if success else "failure",
            "success": success, "seconds": 1.0, "code": "test"}


def no_worker(_grasp_cache: str) -> None:
    pass


def test_the_suite_reports_each_task_and_the_suite_pooled(tmp_path, monkeypatch):
    from evaluation.suite import run_suite

    monkeypatch.setattr(protocol, "run_episode", fake_trial)
    report = run_suite(tmp_path, quick=True, workers=1, trials=2, world="exact", tasks=("paper", "pose"),
                       methods=("gd2p-closed-critic-p24", "fixed-corrected"), worker_init=no_worker)
    assert report == tmp_path / "suite-exact" / "report.md"
    text = report.read_text()
    assert "## Task `paper`" in text and "## Task `pose`" in text and "## The suite" in text
    assert text.count("Against the tolerance") == 2 and "unpredicted" in text  # the fixed pose's failures, by cause
    summary = json.loads((tmp_path / "suite-exact" / "summary.json").read_text())
    assert summary["runs"] == {"paper": "closed-loop-exact", "pose": "closed-loop-exact-pose"}
    assert summary["suite"]["gd2p-closed-critic-p24"]["interval_95"]["value"] == 1.0
    assert summary["suite"]["fixed-corrected"]["interval_95"]["value"] == pytest.approx(0.5)
    assert summary["suite"]["differences_95"]["gd2p-closed-critic-p24 - fixed-corrected"]["value"] == pytest.approx(0.5)
    pose_records = (tmp_path / "closed-loop-exact-pose" / "records.jsonl").read_text().splitlines()
    assert all(json.loads(line)["task"] == "pose" for line in pose_records)
    # resumed: nothing is run again, the report is the same
    monkeypatch.setattr(protocol, "run_episode", lambda e: pytest.fail(f"ran {e.key} again"))
    run_suite(tmp_path, quick=True, workers=1, trials=2, world="exact", tasks=("paper", "pose"),
              methods=("gd2p-closed-critic-p24", "fixed-corrected"), worker_init=no_worker)


def test_the_cli_refuses_an_unknown_task_and_tasks_outside_the_suite():
    def gd2p(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "cli.main", "eval", *args], cwd=ROOT, capture_output=True,
                              text=True, timeout=120)

    unknown = gd2p("suite", "--tasks", "stack")
    assert unknown.returncode == 2 and "unknown task(s) stack; known: paper, pose" in unknown.stderr
    elsewhere = gd2p("methods", "--tasks", "pose")
    assert elsewhere.returncode == 2 and "--tasks applies to suite and closed-loop only" in elsewhere.stderr
    several = gd2p("closed-loop", "--tasks", "wall,clutter")
    assert several.returncode == 2 and "--tasks takes one task" in several.stderr


@pytest.mark.parametrize("task", ["tall", "flat", "small", "round"])
def test_a_shape_task_draws_fresh_objects_of_its_class_from_several_families(task):
    from evaluation.methods import protocol_for
    from shared.world.objects.catalog import resolve_library_id

    spec = protocol_for("closed-loop", quick=False, task=task)
    assert len(spec.objects) == 6 and spec.directory_name == f"closed-loop-real-{task}"
    assert all(protocol.default_shape(o) == task for o in spec.objects)
    assert not set(spec.objects) & set(protocol.PROCEDURAL_OBJECTS + protocol.EVERYDAY_OBJECTS)  # not the 14 developed on
    if task in ("tall", "flat"):
        assert len({resolve_library_id(o).family for o in spec.objects}) >= 3
    assert protocol_for("closed-loop", quick=False, split="val", task=task).objects != spec.objects


def test_a_split_without_enough_objects_of_a_class_is_refused():
    with pytest.raises(ValueError, match="objects of class 'round'; the task needs 500"):
        protocol.shape_task_objects("round", "test", 500)


def test_the_tasks_picture_shows_each_tasks_scene(tmp_path):
    from PIL import Image

    from evaluation.suite import main

    def red_pixels(task: str) -> int:  # the wall is red (so are the world's x axis and the legend's swatch)
        out = tmp_path / f"{task}.png"
        assert main(["--draw", str(out), "--tasks", task]) == 0
        with Image.open(out) as picture:
            pixels = np.asarray(picture.convert("RGB")).reshape(-1, 3).astype(int)
        return int(np.sum((pixels[:, 0] > 150) & (pixels[:, 1] < 80) & (pixels[:, 2] < 80)))

    assert red_pixels("wall") > red_pixels("clutter") + 1000
    with pytest.raises(SystemExit):
        main(["--draw", str(tmp_path / "x.png"), "--tasks", "stack"])

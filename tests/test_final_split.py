"""The final split: its objects, the content-hash freeze, the guard that lets only
`gd2p eval EXPERIMENT --split final` load them, the clean-tree refusal and the run log."""
from __future__ import annotations

import argparse
import hashlib
import json
import re
import subprocess
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from evaluation import final_run
from evaluation import push_protocol as protocol
from evaluation.methods import protocol_for
from shared.world.objects import FAMILIES, assert_split, list_object_ids, load_object, split_of
from shared.world.objects import final_split as fs
from shared.world.objects.catalog import library_ids, resolve_library_id, resolve_source
from shared.world.objects.errors import ObjectLoadError, SplitError
from shared.world.objects.model import load_library_object

ROOT = Path(__file__).resolve().parents[1]


def test_final_split_draws_every_family_afresh_and_a_new_family_nothing_trains_on():
    ids = fs.final_ids()
    assert len(ids) >= 60 and len(set(ids)) == len(ids)
    families = {fs.final_spec(i).family for i in ids}
    assert families == set(FAMILIES) | {"round"}
    assert "round" not in FAMILIES  # not a library family: no dataset, index or critic can hold one
    assert not set(ids) & set(library_ids()) and all(split_of(i) == "final" for i in ids)
    # fresh draws, not copies of library objects: no final object has a library object's parameters
    library_params = {json.dumps(_params(f"proc-{f}-{n:03d}"), sort_keys=True)
                      for f in FAMILIES for n in range(10)}
    assert not {json.dumps(fs.final_spec(i).params, sort_keys=True) for i in ids} & library_params
    kinds = {fs.final_spec(f"final-round-{n:02d}").params["kind"] for n in range(fs.ROUND_COUNT)}
    assert kinds == {0.0, 1.0, 2.0}  # balls, standing fruit, lying fruit


def _params(object_id: str) -> dict[str, float]:
    from shared.world.objects.procedural import procedural_spec

    return procedural_spec(object_id).params


def test_the_committed_manifest_freezes_every_final_object():
    manifest = fs.read_manifest()
    assert sorted(manifest) == sorted(fs.final_ids())
    assert fs.load_final_split() == fs.final_ids()  # every mesh hashes as frozen


def test_a_changed_generator_is_refused_naming_the_object(monkeypatch, tmp_path):
    from shared.world.objects import procedural

    original = procedural._BUILDERS["box"]

    def wider(params):
        mesh = original(params)
        mesh.apply_scale([1.01, 1.0, 1.0])
        return mesh

    monkeypatch.setitem(procedural._BUILDERS, "box", wider)
    with pytest.raises(fs.FinalSplitChangedError, match="final-box-00: its generator now makes a different mesh"):
        fs.load_final_split()
    fs.checked_mesh("final-cone-00")  # the other families are untouched
    with fs.final_split_access(), pytest.raises(fs.FinalSplitChangedError, match="final-box-01"):
        load_object("final-box-01", cache_dir=tmp_path / "cache")  # a load reads the mesh through the same check
    # a manifest that no longer lists the split's objects is refused too
    manifest = json.loads(fs.MANIFEST_PATH.read_text())
    del manifest["objects"]["final-round-03"]
    path = tmp_path / "final_split.json"
    path.write_text(json.dumps(manifest))
    with pytest.raises(fs.FinalSplitChangedError, match=r"missing \['final-round-03'\]"):
        fs.load_final_split(path)


def test_final_ids_are_refused_everywhere_outside_the_guard():
    assert not fs.final_access_open()
    object_id = "final-round-00"
    for load in (load_object, load_library_object, resolve_source, resolve_library_id):
        with pytest.raises(fs.FinalSplitAccessError, match=r"final-round-00 is an object of the final split.*--split final"):
            load(object_id)
    assert issubclass(fs.FinalSplitAccessError, ObjectLoadError) and issubclass(fs.FinalSplitAccessError, SplitError)
    with pytest.raises(SplitError):
        assert_split(object_id, "train")  # training's guard
    assert not any(fs.is_final_id(i) for i in list_object_ids())  # `gd2p objects list`, dataset builds, indexes

    from shared.contracts.messages import ObjectRef
    from shared.data_engine import BuildError, select_objects
    from shared.world.object_refs import load_object_ref

    with pytest.raises(fs.FinalSplitAccessError):  # the planner's and the sampler's loads by id
        load_object_ref(ObjectRef(library_id=object_id))
    with pytest.raises(BuildError, match="final split"):
        select_objects("train", object_ids=[object_id])


def test_gd2p_push_refuses_a_final_object_before_any_request(capsys):
    from cli.main import main

    assert main(["push", "--object", "final-box-00", "--direction-deg", "0"]) == 2
    assert "final-box-00 is an object of the final split" in capsys.readouterr().err


def test_only_the_final_split_evaluation_opens_the_access():
    allowed = {"shared/world/objects/final_split.py", "evaluation/final_run.py"}
    pattern = re.compile(r"final_split_access|_holders")
    offenders = [str(path.relative_to(ROOT)) for path in ROOT.rglob("*.py")
                 if ".venv" not in path.parts and path.parts[len(ROOT.parts)] != "tests"
                 and str(path.relative_to(ROOT)) not in allowed and pattern.search(path.read_text(encoding="utf-8"))]
    assert offenders == []


def test_a_final_episode_builds_inside_the_guard():
    with fs.final_split_access():
        spec = protocol_for("closed-loop", quick=True, split="final")
        assert spec.directory_name == "closed-loop-real-final" and all(fs.is_final_id(o) for o in spec.objects)
        episode = protocol.episodes(["gd2p"], "allegro", spec.objects[-1:], [60.0], 1, split="final")[0]
        T = protocol.placement(episode)  # the object loads: a round fruit resting near the spot in front of the robot
        assert np.linalg.norm(T[:2, 3] - np.array(protocol.OBJECT_XY)) < 0.02
        assert spec.settings()["split"] == "final"
    assert not fs.final_access_open()
    # the final trials' placements and world draws have seeds of their own
    def unsalted(text: str) -> int:
        return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "little") & 0x7FFFFFFF

    assert episode.seed != unsalted(f"{episode.object_id}/60/0")
    assert episode.world_seed != unsalted(f"world/{episode.object_id}/60/0")
    plain = protocol.Episode("gd2p", "allegro", "proc-box-000", 60.0, 0)  # development seeds are those they were
    assert (plain.seed, plain.world_seed) == (unsalted("proc-box-000/60/0"), unsalted("world/proc-box-000/60/0"))
    with pytest.raises(ValueError, match="uses final objects only"):  # a development object is not a final trial
        protocol.episodes(["gd2p"], "allegro", ["proc-box-000"], [60.0], 1, split="final")


def _git_repo(path: Path) -> Path:
    def git(*args: str) -> None:
        subprocess.run(["git", "-C", str(path), *args], check=True, capture_output=True)

    path.mkdir(parents=True, exist_ok=True)
    git("init", "-q")
    git("config", "user.email", "t@example.com")
    git("config", "user.name", "t")
    (path / "code.py").write_text("x = 1\n")
    git("add", "code.py")
    git("commit", "-qm", "init")
    return path


def test_a_dirty_tree_is_refused_before_anything_runs(tmp_path):
    repo = _git_repo(tmp_path / "repo")
    commit = final_run.clean_commit(repo)
    assert re.fullmatch(r"[0-9a-f]{40}", commit)
    (repo / "notes.txt").write_text("untracked files do not count\n")
    assert final_run.clean_commit(repo) == commit
    (repo / "code.py").write_text("x = 2\n")
    with pytest.raises(final_run.FinalRunError, match=r"clean tree only.*code\.py"):
        final_run.clean_commit(repo)
    ran = []
    with pytest.raises(final_run.FinalRunError):
        final_run.run_final("methods", lambda *a, **k: ran.append(1), tmp_path / "out", quick=True, workers=1,
                            command="gd2p eval methods --split final", options={}, repo=repo)
    assert ran == [] and not final_run.log_path(repo).exists()
    with pytest.raises(final_run.FinalRunError, match="git checkout"):
        final_run.clean_commit(tmp_path / "not-a-repo")


def test_every_final_run_is_logged_good_or_bad(tmp_path):
    repo = _git_repo(tmp_path / "repo")
    commit = final_run.clean_commit(repo)
    calls = []

    def fake_run(out, *, quick, workers, split, worker_init, **options):
        calls.append((split, worker_init, fs.final_access_open(), options))
        report = out / "methods-real-camera3-final" / "report.md"
        report.parent.mkdir(parents=True, exist_ok=True)
        report.write_text("report")
        return report

    report = final_run.run_final("methods", fake_run, repo / "results", quick=False, workers=2,
                                 command="gd2p eval methods --split final", options={"world": "real", "cameras": 3},
                                 repo=repo)
    assert report.name == "report.md"
    assert calls == [("final", final_run._init_final_worker, True, {"world": "real", "cameras": 3})]
    assert not fs.final_access_open()

    def failing_run(*args, **kwargs):
        raise RuntimeError("the planner crashed")

    with pytest.raises(RuntimeError):
        final_run.run_final("leap", failing_run, repo / "results", quick=True, workers=1,
                            command="gd2p eval leap --split final --quick", options={}, repo=repo)
    text = final_run.log_path(repo).read_text()
    assert text.startswith("# Final-split runs") and text.count("# Final-split runs") == 1
    first, second = text.splitlines()[-2:]
    assert commit[:12] in first and "`gd2p eval methods --split final`" in first
    assert "cameras=3" in first and "manifest=" in first and "results/methods-real-camera3-final/summary.json" in first
    assert "`gd2p eval leap --split final --quick`" in second and "failed: RuntimeError: the planner crashed" in second


def _eval_args(*argv: str) -> argparse.Namespace:
    from cli import eval as eval_cli

    parser = argparse.ArgumentParser()
    eval_cli.register(parser.add_subparsers())
    return parser.parse_args(["eval", *argv])


def test_split_dev_is_the_default_and_test_an_alias_that_says_so(monkeypatch, capsys, tmp_path):
    from cli import eval as eval_cli

    seen = []
    monkeypatch.setattr(eval_cli, "experiment_function",
                        lambda name: lambda out, **options: seen.append(options) or out / "report.md")
    monkeypatch.setattr("evaluation.report.write_index", lambda out: out / "README.md")
    assert eval_cli.run(_eval_args("methods", "--out", str(tmp_path))) == 0
    assert eval_cli.run(_eval_args("methods", "--split", "test", "--out", str(tmp_path))) == 0
    assert seen[0] == seen[1] and "split" not in seen[0]  # the same run, the same results directory
    assert "--split test is the development split, now named dev" in capsys.readouterr().err
    assert eval_cli.run(_eval_args("sampler-quality", "--split", "dev", "--out", str(tmp_path))) == 0
    assert seen[-1]["split"] == "test"  # the object library's name for the development split


def test_split_final_goes_through_the_guarded_entry_point_only(monkeypatch, capsys, tmp_path):
    from cli import eval as eval_cli

    assert eval_cli.run(_eval_args("sampler-quality", "--split", "final")) == 2
    assert "--split final applies to methods, leap, closed-loop" in capsys.readouterr().err

    def dirty(repo=None):
        raise final_run.FinalRunError("the final split runs from a clean tree only; commit or stash: cli/eval.py")

    monkeypatch.setattr(final_run, "clean_commit", dirty)
    assert eval_cli.run(_eval_args("methods", "--split", "final", "--out", str(tmp_path))) == 2
    assert "clean tree only" in capsys.readouterr().err
    assert "--split final" in eval_cli.__doc__ and "dev" in eval_cli.__doc__


def test_final_trials_spread_over_objects_one_direction_each_and_every_object_of_a_class():
    """The final split spends its trials on objects: each meets one direction, the same in every task (tasks pair),
    a third of them each direction; a shape task measures every final object of its class, the new round family's
    balls and lying fruit among the rollers."""
    with fs.final_split_access():
        paper = protocol_for("closed-loop", quick=False, trials=1, split="final", methods=("gd2p",))
        episodes = paper.episodes()
        assert len(episodes) == len(fs.final_ids()) == len({e.object_id for e in episodes})
        per_direction = Counter(e.direction_deg for e in episodes)
        assert set(per_direction) == set(protocol.DIRECTIONS_DEG) and max(per_direction.values()) - min(per_direction.values()) <= 1
        # half the objects meet each task's mirror case (a clockwise goal, the wall on the other side), in every direction
        assert Counter((e.direction_deg, e.mirrored) for e in episodes) == {(d, m): 12 for d in protocol.DIRECTIONS_DEG
                                                                           for m in (False, True)}
        wall = protocol_for("closed-loop", quick=False, trials=1, split="final", methods=("gd2p",), task="wall")
        assert {(e.object_id, e.direction_deg) for e in wall.episodes()} == {(e.object_id, e.direction_deg) for e in episodes}
        round_task = protocol_for("closed-loop", quick=False, trials=1, split="final", methods=("gd2p",), task="round")
        assert {"final-round-00", "final-round-02", "final-lying-00"} <= set(round_task.objects)  # a ball, a lying fruit
        small = protocol_for("closed-loop", quick=False, trials=1, split="final", methods=("gd2p",), task="small")
        assert small.objects == tuple(f"final-small-{i:02d}" for i in range(fs.FINAL_PER_FAMILY))
    development = protocol_for("closed-loop", quick=True, trials=1, methods=("gd2p",))
    assert len(development.episodes()) == len(development.objects) * len(protocol.DIRECTIONS_DEG)  # all three there


def test_a_final_runs_worker_process_keeps_its_access_open():
    """A final run's trials run in spawned workers, each opening the access for its life: it must stay open after
    the initializer returns (an unreferenced open context is collected, and closes it), and only there."""
    import multiprocessing as mp

    with mp.get_context("spawn").Pool(1, initializer=final_run.open_access_for_life) as pool:
        assert pool.apply(fs.final_access_open)
    with mp.get_context("spawn").Pool(1) as pool:
        assert not pool.apply(fs.final_access_open)

"""Coverage measurement (evaluation/coverage.py): exact early stopping, resumable records, data-size subset."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from evaluation.coverage import (
    CoverageError,
    CoverageSettings,
    PushTally,
    measure_coverage,
    measure_object,
    push_until_covered,
    summarize,
    validated_spread_cm,
)
from evaluation.data_size import object_subset
from evaluation.store import ResultStore, ResultStoreError
from shared.robots.hands import load_hand
from shared.validation.augment import halton_perturbations
from shared.validation.push import table_object
from shared.validation.validator import Validator
from shared.world.fixed_poses import spatula_pose
from shared.world.objects import load_object, split_of

BOX_ID = "proc-box-001"  # 19 x 11 x 8 cm: the spatula pose pushes it to the goal


@dataclass(frozen=True)
class ScriptedSource:
    """`failing` copies of the spatula pose moved past the box (the hand never touches it), then
    `spatula` Halton-perturbed spatula poses (which push it). Module-level, so spawn workers can unpickle it."""

    failing: int
    spatula: int

    def label(self) -> str:
        return "scripted"

    def poses(self, obj, frame, k, seed) -> np.ndarray:
        hand = load_hand("allegro")
        vertices = table_object(obj).vertices_d
        pose = spatula_pose(hand, vertices)
        far_side = pose + np.r_[np.ptp(vertices[:, 0]) + 0.10, np.zeros(24)]
        lower, upper = hand.joint_lower.double().numpy(), hand.joint_upper.double().numpy()
        near = halton_perturbations(pose, self.spatula, seed, lower, upper) if self.spatula else np.zeros((0, 25))
        return np.concatenate([np.repeat(far_side[None], self.failing, axis=0), near])[:k]


@dataclass(frozen=True)
class RefusingSource:
    """A source that must not be asked for poses (everything is already recorded)."""

    def label(self) -> str:
        return "refusing"

    def poses(self, obj, frame, k, seed) -> np.ndarray:
        raise AssertionError(f"{obj.id} was measured again")


def _push_all(source: ScriptedSource, settings: CoverageSettings) -> list[bool]:
    obj = load_object(BOX_ID)
    poses = source.poses(obj, None, settings.samples, 0)
    with Validator() as validator:
        return [o.success for o in validator.validate(table_object(obj), load_hand("allegro"), poses).outcomes]


@pytest.mark.parametrize("source", [ScriptedSource(failing=7, spatula=5), ScriptedSource(failing=6, spatula=0)],
                         ids=["success-after-chunks", "no-success"])
def test_early_stopping_matches_pushing_every_pose(source):
    settings = CoverageSettings(samples=12, fraction_poses=4, chunk=3, seed=0)
    record = measure_object(source, BOX_ID, settings)
    full = _push_all(source, settings)

    assert record["any_success"] == any(full)
    assert record["first_success_index"] == (full.index(True) if any(full) else None)
    assert record["validated_fraction"] == sum(full[:4]) / 4
    # the first 4 are the hand beyond the box, pushing away from it
    assert record["failures"] == {"turned": 0, "toppled": 0, "missed": 0, "no contact": 4}
    if any(full):  # stopped at the end of the chunk holding the first success
        assert record["n_validated"] == min(len(full), 4 + 3 * -(-(full.index(True) + 1 - 4) // 3))
        assert record["n_validated"] < len(full)
    else:
        assert record["n_validated"] == len(full)


def test_the_spread_of_validated_poses_sees_one_pose_repeated_and_ignores_failures():
    """A source that repeats one good pose must not look as varied as one that validates poses all over the object."""
    positions = np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.0, 0.04, 0.0], [5.0, 5.0, 5.0]])
    poses = np.zeros((4, 25))
    poses[:, :3] = positions
    varied = PushTally(4, [True, True, True, False], fraction_poses=4)  # the far pose failed: not counted
    expected = np.sqrt(((positions[:3] - positions[:3].mean(0)) ** 2).sum(1).mean()) * 100
    assert validated_spread_cm(poses, varied) == pytest.approx(expected, abs=1e-3)
    repeated = np.zeros((4, 25))
    assert validated_spread_cm(repeated, PushTally(4, [True] * 4, fraction_poses=4)) == 0.0
    assert validated_spread_cm(poses, PushTally(4, [False, True, False, False], fraction_poses=4)) is None


def test_early_stopping_never_changes_any_success_on_random_outcomes():
    rng = np.random.default_rng(0)
    for _ in range(500):
        n = int(rng.integers(1, 60))
        outcomes = rng.random(n) < rng.choice([0.0, 0.02, 0.2])
        pushed: list[int] = []

        def push(start: int, stop: int, pushed: list[int] = pushed, outcomes: np.ndarray = outcomes) -> list[bool]:
            pushed.extend(range(start, stop))
            return list(outcomes[start:stop])

        tally = push_until_covered(n, push, fraction_poses=10, chunk=4)
        assert (tally.first_success_index is not None) == bool(outcomes.any())
        assert pushed == list(range(len(pushed)))  # in order, each pose once
        assert len(pushed) >= min(10, n)
        if not outcomes.any():
            assert len(pushed) == n


def test_records_resume_and_settings_are_pinned(tmp_path):
    settings = CoverageSettings(samples=3, fraction_poses=2, chunk=1, seed=0)
    objects = [BOX_ID, "proc-box-002"]
    pinned = {"coverage": settings.to_dict(), "objects": objects}
    first = measure_coverage(ScriptedSource(failing=1, spatula=2), objects, ResultStore(tmp_path, pinned), "scripted",
                             settings, workers=2, progress=False)
    assert [r["object"] for r in first] == objects
    assert all(r["n_validated"] >= 2 for r in first)

    again = measure_coverage(RefusingSource(), objects, ResultStore(tmp_path, pinned), "scripted", settings,
                             workers=1, progress=False)
    assert again == first
    assert summarize(again)["objects"] == 2

    with pytest.raises(ResultStoreError, match="coverage"):
        ResultStore(tmp_path, {**pinned, "coverage": CoverageSettings(samples=200).to_dict()})


def test_data_size_object_subset_is_fixed_and_from_the_test_split():
    subset = object_subset(20)
    assert subset == object_subset(20)
    assert len(set(subset)) == 20 and all(split_of(i) == "test" for i in subset)
    assert object_subset(8) == subset[:8]  # a larger subset extends a smaller one
    assert object_subset(20, seed=1) != subset


@dataclass(frozen=True)
class TurnedSpatulaSource:
    """The spatula pose for the object as the frame places it (turned), from the frame alone."""

    def label(self) -> str:
        return "turned spatula"

    def poses(self, obj, frame, k, seed) -> np.ndarray:
        from shared.frames import frame_object_transform, frame_transform, invert_transform

        T_D_O = invert_transform(frame_transform(frame)) @ frame_object_transform(frame)
        vertices = obj.mesh.vertices @ T_D_O[:3, :3].T + T_D_O[:3, 3]
        return spatula_pose(load_hand("allegro"), vertices)[None]


def test_random_yaw_turns_each_object_by_its_own_seeded_yaw_and_the_push_sees_the_same_placement():
    from evaluation.coverage import coverage_frame, object_yaw_rad
    from shared.frames import object_yaw_in_d

    settings = CoverageSettings(samples=1, fraction_poses=1, chunk=1, yaw="random")
    yaws = [object_yaw_rad(settings, oid) for oid in (BOX_ID, "proc-box-002", "rnd-000")]
    assert len(set(yaws)) == 3 and all(-np.pi <= y < np.pi and y != 0.0 for y in yaws)
    assert object_yaw_rad(CoverageSettings(), BOX_ID) == 0.0
    assert object_yaw_rad(settings, BOX_ID) == yaws[0]  # from (seed, object) only

    box = load_object(BOX_ID)
    frame = coverage_frame(box, settings, BOX_ID)
    turned = object_yaw_in_d(frame, box.default_pose.rotation)
    assert np.isclose(np.angle(np.exp(1j * (turned - yaws[0]))), 0.0, atol=1e-9)

    # A pose made for the turned box pushes the box the validator placed: both saw one placement.
    record = measure_object(TurnedSpatulaSource(), BOX_ID, settings)
    assert record["any_success"] and record["validated_fraction"] == 1.0


def test_coverage_settings_reject_an_unknown_yaw_and_keep_the_old_pin_at_yaw_zero():
    from evaluation.coverage import CoverageError

    with pytest.raises(CoverageError, match="yaw"):
        CoverageSettings(yaw="sideways")
    assert "yaw" not in CoverageSettings().to_dict()  # stores made before the setting still resume
    assert CoverageSettings(yaw="random").to_dict()["yaw"] == "random"


def test_sampler_quality_subsets_take_every_family_in_turn_and_never_the_train_split():
    from evaluation.coverage import CoverageError
    from evaluation.sampler_quality import family_of, quality_objects

    subset = quality_objects(split="test", count=40)
    assert all(split_of(i) == "test" for i in subset) and len(set(subset)) == 40
    families = {family_of(i) for i in quality_objects(split="test")}
    assert {family_of(i) for i in subset} == families  # the unseen mug family included
    assert quality_objects(split="val", count=12) == quality_objects(split="val", count=30)[:12]
    with pytest.raises(CoverageError, match="train"):
        quality_objects(split="train")


def test_data_size_first_protocol_keeps_its_pin_and_objects():
    """The committed first run (yaw 0, seeded hash subset) still resumes under the v2-capable settings."""
    import json

    from evaluation.data_size import FULL, test_objects

    pinned = json.loads((Path(__file__).resolve().parents[1] / "results" / "data-size" / "settings.json").read_text())
    assert {k: v for k, v in pinned.items() if k not in ("objects", "dataset_sha256")} == FULL.to_dict()
    assert test_objects(FULL) == pinned["objects"]


def test_data_size_at_random_yaw_measures_every_family_and_reports_the_unseen_one():
    import dataclasses

    from evaluation.data_size import FULL, model_name, table_rows, test_objects
    from shared.world.objects import UNSEEN_FAMILIES
    from shared.world.objects.catalog import resolve_library_id

    settings = dataclasses.replace(FULL, yaw="random", seeds=(0, 1), fractions=(0.5, 1.0), test_objects=40)
    objects = test_objects(settings)
    families = {resolve_library_id(o).family for o in objects}
    assert len(objects) == 40 and all(split_of(o) == "test" for o in objects)
    assert set(UNSEEN_FAMILIES) <= families and len(families) >= 12
    assert "yaw" in settings.to_dict()["coverage"]  # a random-yaw run cannot resume a yaw-0 store
    assert "lr" not in settings.to_dict() and dataclasses.replace(settings, lr=1e-3).to_dict()["lr"] == 1e-3
    # a run in the drawn world cannot resume an exact store either, and pushes its poses there
    real = dataclasses.replace(settings, world="real", cameras=3)
    assert real.to_dict()["coverage"]["world"] == "real" and real.coverage().cameras == 3
    assert "world" not in settings.to_dict()["coverage"]

    mug = next(o for o in objects if resolve_library_id(o).family in UNSEEN_FAMILIES)
    other = next(o for o in objects if resolve_library_id(o).family not in UNSEEN_FAMILIES)

    def record(obj: str, successes: int) -> dict:
        return {"object": obj, "fraction_pushed": 10, "fraction_successes": successes, "validated_fraction": successes / 10,
                "any_success": successes > 0, "n_validated": 10, "seconds": 1.0}

    coverage = {model_name(f, s): [record(mug, 8 if f == 1.0 else 2), record(other, 4 + s)]
                for f in settings.fractions for s in settings.seeds}
    models = {name: {"train_objects": 10, "train_poses": 100, "final_val_loss": 0.1} for name in coverage}
    rows = table_rows(settings, models, coverage)
    assert [r["fraction"] for r in rows] == [0.5, 1.0]
    # pooled over both seeds: (2 + 4 + 2 + 5) / 40 and (8 + 4 + 8 + 5) / 40
    assert rows[0]["validated_fraction"]["value"] == pytest.approx(13 / 40)
    assert rows[1]["validated_fraction"]["value"] == pytest.approx(25 / 40)
    assert rows[1]["unseen_family"]["value"] == pytest.approx(0.8) and rows[1]["unseen_family"]["objects"] == 1
    assert rows[0]["validated_fraction"]["low"] <= rows[0]["validated_fraction"]["value"] <= rows[0]["validated_fraction"]["high"]


def test_eval_refuses_a_checkpoint_for_an_experiment_that_would_not_use_it(capsys):
    """`gd2p eval leap --checkpoint X` would run the shipped models while the user thinks X ran: refused."""
    from cli.main import main

    assert main(["eval", "leap", "--checkpoint", "x.pt", "--tag", "x", "--out", "/tmp/never-written"]) == 2
    err = capsys.readouterr().err
    assert "--checkpoint apply to sampler-quality only" in err and "GD2P_SAMPLER_CHECKPOINT_<HAND>" in err
    assert main(["eval", "methods", "--nn-index", "x.npz", "--out", "/tmp/never-written"]) == 2
    assert "--nn-index apply to sampler-quality only" in capsys.readouterr().err


def test_eval_sees_the_object_through_three_cameras_under_real_and_is_told_the_mesh_under_exact(monkeypatch, capsys):
    import cli.eval
    from cli.main import main

    calls = []

    def experiment(out, quick, workers, **options):
        calls.append(options)
        return out / "report.md"

    monkeypatch.setattr(cli.eval, "experiment_function", lambda name: experiment)
    monkeypatch.setattr("evaluation.report.write_index", lambda out: out / "README.md")
    for argv, cameras in ((["methods"], 3), (["leap", "--world", "exact"], 0), (["methods", "--cameras", "0"], 0),
                          (["closed-loop", "--world", "exact", "--cameras", "1"], 1), (["multistep"], 3),
                          (["multistep", "--world", "exact"], 0), (["multistep", "--cameras", "0", "--closed-loop"], 0)):
        calls.clear()
        assert main(["eval", *argv, "--out", "/tmp/never-written"]) == 0
        assert calls[0]["cameras"] == cameras, argv
    for argv, world, cameras in ((["sampler-quality"], "real", 3), (["data-size", "--world", "exact"], "exact", 0),
                                 (["sampler-quality", "--cameras", "0"], "real", 0)):
        calls.clear()
        assert main(["eval", *argv, "--out", "/tmp/never-written"]) == 0
        assert (calls[0]["world"], calls[0]["cameras"]) == (world, cameras), argv
    assert main(["eval", "sampler-diagnosis", "--cameras", "3", "--out", "/tmp/never-written"]) == 2
    assert "--cameras applies to methods, leap, closed-loop, suite, multistep, sampler-quality, data-size" in capsys.readouterr().err


def test_eval_refuses_a_noise_scale_outside_sampler_quality_or_out_of_range(capsys):
    from cli.main import main

    assert main(["eval", "methods", "--noise-scale", "0.5", "--out", "/tmp/never-written"]) == 2
    err = capsys.readouterr().err
    assert "--noise-scale apply to sampler-quality only" in err and "GD2P_SAMPLER_NOISE_SCALE" in err
    for bad in ("0", "1.5", "-0.2"):
        assert main(["eval", "sampler-quality", "--noise-scale", bad, "--tag", "x", "--out", "/tmp/never-written"]) == 2
        assert "--noise-scale must be in (0, 1]" in capsys.readouterr().err


def test_eval_passes_critic_guidance_to_sampler_quality_and_refuses_it_elsewhere_or_malformed(monkeypatch, capsys):
    import cli.eval
    from cli.main import main
    from shared.sampling.diffusion import GradientGuidance

    calls = []
    monkeypatch.setattr(cli.eval, "experiment_function", lambda name: lambda out, quick, workers, **o: calls.append(o) or out)
    monkeypatch.setattr("evaluation.report.write_index", lambda out: out / "README.md")
    assert main(["eval", "sampler-quality", "--critic-guidance", "0.02", "--guided-steps", "20", "--tag", "g",
                 "--out", "/tmp/never-written"]) == 0
    assert calls[0]["guidance"] == GradientGuidance(0.02, steps=20)
    for argv, message in ((["methods", "--critic-guidance", "0.02"], "apply to sampler-quality only"),
                          (["sampler-quality", "--guided-steps", "5"], "--guided-steps needs --critic-guidance"),
                          (["sampler-quality", "--critic-guidance", "0"], "step scale must be > 0"),
                          (["sampler-quality", "--critic-guidance", "0.1", "--guided-steps", "101"], "guided steps")):
        assert main(["eval", *argv, "--out", "/tmp/never-written"]) == 2, argv
        assert message in capsys.readouterr().err, argv


def test_eval_refuses_data_size_flags_elsewhere_and_bad_seeds(capsys):
    from cli.main import main

    assert main(["eval", "methods", "--seeds", "0", "--out", "/tmp/never-written"]) == 2
    assert "apply to data-size only" in capsys.readouterr().err
    assert main(["eval", "sampler-quality", "--lr", "1e-3", "--out", "/tmp/never-written"]) == 2
    assert "--lr apply to data-size only" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["eval", "data-size", "--lr", "0"])
    with pytest.raises(SystemExit):
        main(["eval", "data-size", "--seeds", "0,0"])
    assert "distinct seeds" in capsys.readouterr().err


def test_sampler_quality_takes_the_hand_a_checkpoint_was_trained_for_and_its_index():
    from evaluation.sampler_quality import checkpoint_hand, nearest_neighbor_index, shipped_checkpoint, shipped_nn_index

    assert checkpoint_hand(shipped_checkpoint("leap")) == "leap"
    assert checkpoint_hand(shipped_checkpoint()) == "allegro"
    assert nearest_neighbor_index(Path("/tmp/never-written"), hand="leap") == shipped_nn_index("leap")


def test_critic_order_puts_the_samples_the_critic_likes_first_and_refuses_another_checkpoints_critic():
    from evaluation.coverage import CriticOrderedSource, DiffusionSource, coverage_frame
    from evaluation.sampler_quality import shipped_checkpoint
    from shared.sampling.critic_train import load_critic, success_probabilities
    from shared.sampling.sampling import PoseSampler

    checkpoint, critic = shipped_checkpoint(), shipped_checkpoint().with_name("allegro_critic.pt")
    obj = load_object("proc-box-000")
    frame = coverage_frame(obj, CoverageSettings(yaw="random"), "proc-box-000")
    drawn = DiffusionSource(str(checkpoint)).poses(obj, frame, 24, seed=3)
    ordered = CriticOrderedSource(DiffusionSource(str(checkpoint)), str(checkpoint), str(critic)).poses(obj, frame, 24, seed=3)
    # The same 24 samples, only reordered, and the critic's probability never rises down the list.
    assert sorted(map(tuple, ordered)) == sorted(map(tuple, drawn))
    sampler = PoseSampler(str(checkpoint))
    points_d, _, _ = sampler.points_in_d(obj, frame)
    scores = success_probabilities(load_critic(critic).model, "allegro", sampler.encode_points(points_d, "box"), points_d,
                                   ordered)
    assert np.all(np.diff(scores) <= 0) and scores[0] > scores[-1]
    wrong = CriticOrderedSource(DiffusionSource(str(checkpoint)), str(checkpoint.with_name("leap.pt")), str(critic))
    with pytest.raises(CoverageError, match="trained for the sampler checkpoint"):
        wrong.poses(obj, frame, 4, seed=0)


def test_critic_guidance_raises_what_the_critic_expects_of_the_samples_and_of_retrieved_poses():
    """Guided samples and climbed retrieved poses score higher by the critic that steered them than the same
    seed's plain samples and the plain retrieved poses."""
    from evaluation.coverage import CriticClimbedSource, DiffusionSource, NearestNeighborSource, coverage_frame
    from evaluation.sampler_quality import shipped_checkpoint, shipped_nn_index
    from shared.sampling.critic_train import load_critic, success_probabilities
    from shared.sampling.diffusion import GradientGuidance

    checkpoint, critic = str(shipped_checkpoint()), str(shipped_checkpoint().with_name("allegro_critic.pt"))
    obj = load_object("proc-box-000")
    frame = coverage_frame(obj, CoverageSettings(yaw="random"), "proc-box-000")
    guidance = GradientGuidance(0.02, steps=5)
    plain = DiffusionSource(checkpoint)
    guided = DiffusionSource(checkpoint, critic=critic, guidance=guidance)
    retrieved = NearestNeighborSource(str(shipped_nn_index()), fill=True)
    climbed = CriticClimbedSource(retrieved, checkpoint, critic, guidance)
    sampler = plain.pose_sampler()
    points_d, _, _ = sampler.points_in_d(obj, frame)
    bps = sampler.encode_points(points_d, "box")

    def mean_score(source) -> float:
        poses = source.poses(obj, frame, 40, seed=3)
        return float(success_probabilities(load_critic(critic).model, "allegro", bps, points_d, poses).mean())

    assert mean_score(guided) > mean_score(plain) + 0.02
    assert mean_score(climbed) > mean_score(retrieved) + 0.02
    assert "critic-guided (step x0.02, last 5 steps" in guided.label() and "climbed the critic" in climbed.label()


def test_sampler_quality_refuses_critic_methods_without_a_critic(tmp_path):
    from evaluation.sampler_quality import methods, shipped_checkpoint, shipped_nn_index

    with pytest.raises(CoverageError, match="need a success critic"):
        methods(shipped_checkpoint(), shipped_nn_index(), ("ddpm100-critic",), critic=tmp_path / "none.pt")
    critic = shipped_checkpoint().with_name("allegro_critic.pt")
    with pytest.raises(CoverageError, match="need the critic guidance's settings"):
        methods(shipped_checkpoint(), shipped_nn_index(), ("ddpm100-guided",), critic=critic)
    assert list(methods(shipped_checkpoint(), shipped_nn_index(), ("nn", "nn-fill"))) == ["nn", "nn-fill"]


# ----------------------------------------------------------------------------- coverage in a drawn world
@dataclass(frozen=True)
class SeenSpatulaSource:
    """The spatula pose (and Halton copies) built from whatever the source is given of the object: a told mesh
    placed by the frame, or a capture's points, in the source's own direction frame."""

    def label(self) -> str:
        return "seen spatula"

    def poses(self, obj, frame, k, seed) -> np.ndarray:
        from shared.frames import frame_transform, points_world_to_d

        hand = load_hand("allegro")
        if isinstance(obj, np.ndarray):
            vertices_d = points_world_to_d(obj, frame_transform(frame))
        else:
            vertices_d = table_object(obj).vertices_d
        pose = spatula_pose(hand, vertices_d)
        lower, upper = hand.joint_lower.double().numpy(), hand.joint_upper.double().numpy()
        return np.concatenate([pose[None], halton_perturbations(pose, k - 1, seed, lower, upper)])


def test_poses_sampled_for_the_cameras_reconstruction_push_the_true_object():
    """With cameras the source gets only the captured points, in the reconstruction's frame (a few mm off the
    true one); its poses are carried into the true object's frame and pushed against the true object."""
    from evaluation.coverage import coverage_frame, coverage_world, sight

    settings = CoverageSettings(samples=4, fraction_poses=4, chunk=1, world="exact", cameras=3)
    obj = load_object(BOX_ID)
    seen = sight(obj, coverage_frame(obj, settings, BOX_ID), coverage_world(obj, settings, BOX_ID))
    assert isinstance(seen.sampler_input, np.ndarray) and seen.sampler_input.shape[1] == 3
    assert 0.0 < np.linalg.norm(seen.T_true_seen[:2, 3]) < 0.01  # perception's own error: millimetres for a box

    record = measure_object(SeenSpatulaSource(), BOX_ID, settings)
    assert record["validated_fraction"] >= 0.75
    assert record["failures"]["not perceived"] == 0 and record["world"]["cameras"] == 3


def test_the_real_world_pushes_the_object_where_it_truly_stands(monkeypatch):
    """Told the mesh at a pose 20 cm off to the side of the truth, every pose misses the true object."""
    import dataclasses

    import evaluation.coverage as coverage
    from shared.world.sim.world import PoseError

    settings = CoverageSettings(samples=3, fraction_poses=3, chunk=1, world="real")
    told = measure_object(SeenSpatulaSource(), BOX_ID, dataclasses.replace(settings, world="exact"))
    assert told["fraction_successes"] >= 2

    drawn = coverage.coverage_world

    def far_off(obj, settings, object_id):
        return dataclasses.replace(drawn(obj, settings, object_id), pose_error=PoseError(dy_m=0.2))

    monkeypatch.setattr(coverage, "coverage_world", far_off)
    record = measure_object(SeenSpatulaSource(), BOX_ID, settings)
    assert record["fraction_successes"] == 0 and record["failures"]["no contact"] == 3
    assert record["world"]["level"] == "real" and record["world"]["pose_error"]["dy_m"] == 0.2


def test_each_object_has_one_world_for_every_source_and_objects_differ():
    from evaluation.coverage import coverage_world

    settings = CoverageSettings(world="real", cameras=3)
    box, other = load_object(BOX_ID), load_object("proc-box-002")
    assert coverage_world(box, settings, BOX_ID).record() == coverage_world(box, settings, BOX_ID).record()
    assert coverage_world(box, settings, BOX_ID).record() != coverage_world(other, settings, "proc-box-002").record()
    assert coverage_world(box, CoverageSettings(), BOX_ID).level == "exact"
    with pytest.raises(CoverageError, match="world must be"):
        CoverageSettings(world="lab")
    with pytest.raises(CoverageError, match="cameras"):
        CoverageSettings(cameras=4)
    # the stores of the first protocol keep their pin: the exact world told the mesh adds nothing to it
    assert "world" not in CoverageSettings().to_dict() and CoverageSettings(world="real", cameras=3).to_dict()["cameras"] == 3


def test_an_object_the_cameras_cannot_reconstruct_fails_all_its_poses(monkeypatch):
    import evaluation.coverage as coverage
    from shared.world.objects import ObjectLoadError

    def blind(obj, frame, world):
        raise ObjectLoadError("the point cloud cannot be reconstructed: no object above the table")

    monkeypatch.setattr(coverage, "sight", blind)
    settings = CoverageSettings(samples=4, fraction_poses=4, world="real", cameras=3)
    record = measure_object(RefusingSource(), BOX_ID, settings)
    assert (record["validated_fraction"], record["any_success"], record["n_validated"]) == (0.0, False, 0)
    assert record["failures"]["not perceived"] == 4 and "no object above the table" in record["not_perceived"]
    assert summarize([record])["failure_shares"]["not perceived"] == 1.0


def test_result_directories_keep_the_first_names_for_the_exact_world():
    from evaluation import data_size, sampler_quality

    out = Path("/tmp/r")
    assert sampler_quality.result_directory(out, "val", "random", "x") == out / "sampler-quality-val-random-yaw-x"
    assert (sampler_quality.result_directory(out, "val", "random", "x", "real", 3)
            == out / "sampler-quality-real-camera3-val-random-yaw-x")
    assert data_size.result_directory(out, "random", "v2") == out / "data-size-random-yaw-v2"
    assert data_size.result_directory(out, "random", "v2", "real", 0) == out / "data-size-real-random-yaw-v2"


def test_the_world_table_pairs_sources_on_the_objects_both_worlds_measured():
    from evaluation.coverage import world_rows

    def record(object_id, successes):
        return {"object": object_id, "fraction_pushed": 4, "fraction_successes": successes, "n_validated": 4,
                "validated_fraction": successes / 4, "any_success": successes > 0, "seconds": 1.0}

    real = {"ddpm": [record("a", 1), record("b", 2)], "nn": [record("a", 0)]}
    exact = {"ddpm": [record("a", 3), record("b", 4), record("c", 4)]}  # "c" was not measured in the real world
    (row,) = world_rows(real, exact)  # "nn" has no exact records: no row
    assert (row["source"], row["objects"]) == ("ddpm", 2)
    assert row["exact"]["value"] == pytest.approx(7 / 8) and row["perceived"]["value"] == pytest.approx(3 / 8)
    assert row["difference"]["value"] == pytest.approx(-0.5)


def test_a_real_run_finds_each_sources_exact_records_in_the_runs_that_measured_the_same_models(tmp_path):
    from evaluation.sampler_quality import exact_records, methods, shipped_checkpoint, shipped_nn_index

    def exact_run(name, keys, world="exact", **settings):
        store = ResultStore(tmp_path / name, {"checkpoint_id": "ckpt", "nn_index": "nn", "objects": ["a", "b"],
                                              "coverage": CoverageSettings(yaw="random", world=world).to_dict(), **settings})
        for key in keys:
            store.add(f"{key}/a", {"object": "a"})

    exact_run("sampler-quality-random-yaw-mine", ["nn"])
    exact_run("sampler-quality-random-yaw-older", ["ddpm100", "nn"])
    exact_run("sampler-quality-random-yaw-other-model", ["ddim10"], nn_index="another")
    exact_run("sampler-quality-real-random-yaw-x", ["ddim10"], world="real")  # a perceived run: never the exact one
    sources = methods(shipped_checkpoint(), shipped_nn_index(), ("ddpm100", "ddim10", "nn"))
    pinned = {"checkpoint_id": "ckpt", "nn_index": "nn", "objects": ["a"]}
    found, text = exact_records(tmp_path, "test", "random", "mine", pinned, sources)
    assert set(found) == {"DDPM-100", "Nearest neighbour"}  # DDIM-10 only in runs of another index or world
    assert "`sampler-quality-random-yaw-mine/` (Nearest neighbour)" in text and "-older/` (DDPM-100)" in text

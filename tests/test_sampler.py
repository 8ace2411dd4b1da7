"""Sampler (issue 9): dataset reader, training, checkpoints, DDPM/DDIM sampling, NN baseline, service, CLI.

Everything runs on a small synthetic store written here in the data engine's layout: a few
procedural train-split objects, each in two placements (yaws), with poses that depend on the
object's geometry (the hand stands behind the object's back face at half its height, fingers
curled more for taller objects). A tiny network keeps training to a second or two.
"""
from __future__ import annotations

import dataclasses
import json
import shutil
import threading
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
import trimesh

from pose_store import write_pose_store
from shared.contracts.messages import DirectionFrame, ObjectPose, ObjectRef, SampleRequest, SampleResponse
from shared.frames import JOINTS, ROTATION_6D, object_yaw_in_d, poses_d_to_world, r6_to_matrix
from shared.sampling.checkpoint import CheckpointError, file_sha256, load_checkpoint, manifest_path, save_checkpoint
from shared.sampling.dataset import (
    DatasetError,
    Frame,
    choose_fraction,
    frame_points,
    load_pose_dataset,
    split_objects,
)
from shared.sampling.diffusion import TRAIN_TIMESTEPS, DiffusionConfigError, GradientGuidance, sample_normalized
from shared.sampling.model import DenoiserConfig, PoseDenoiser
from shared.sampling.nearest_neighbor import NearestNeighborBaseline
from shared.sampling.sampling import PoseSampler, SamplerInputError, default_frame
from shared.sampling.train import (
    RunOptions,
    TrainConfig,
    TrainingError,
    TrainingTensors,
    hand_joint_limits,
    object_balanced_weights,
    train,
)
from shared.world.objects import list_object_ids, load_object

torch.set_num_threads(1)

HAND = "allegro"
TINY_MODEL = DenoiserConfig(object_dim=32, time_dim=32, hidden_dim=64, num_blocks=2)
YAWS = (0.0, 1.2)
POSES_PER_FRAME = 40


def tiny_config(**changes) -> TrainConfig:
    settings = dict(steps=300, batch_size=64, lr=1e-3, warmup_steps=20, val_fraction=0.2, seed=0, model=TINY_MODEL)
    settings.update(changes)
    return TrainConfig(**settings)


def quiet(**changes) -> RunOptions:
    settings = dict(progress=False, val_every=100, checkpoint_every=100)
    settings.update(changes)
    return RunOptions(**settings)


# ----------------------------------------------------------------------------- synthetic store
def synthetic_objects() -> list[str]:
    train_ids = list_object_ids("train")
    return [i for family in ("box", "cylinder", "hull") for i in [x for x in train_ids if x.startswith(f"proc-{family}-")][:2]]


def synthetic_poses(object_id: str, yaw: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """Poses behind the object's back face (-x in D), at half its height, curl growing with height."""
    points = frame_points(Frame(object_id, -1, yaw))
    back, height = points[:, 0].min(), points[:, 2].max()
    lower, upper = (t.numpy() for t in hand_joint_limits(HAND))
    poses = np.zeros((n, 25), dtype=np.float32)
    poses[:, 0] = back - 0.03 + rng.normal(0, 0.004, n)
    poses[:, 1] = rng.normal(0, 0.01, n)
    poses[:, 2] = 0.5 * height + rng.normal(0, 0.004, n)
    tilt = rng.normal(0, 0.05, n)  # palm facing +x, small tilt about z
    poses[:, 3:6] = np.stack([np.zeros(n), np.zeros(n), -np.ones(n)], axis=1)
    poses[:, 6:9] = np.stack([np.cos(tilt), np.sin(tilt), np.zeros(n)], axis=1)
    curl = np.clip(height / 0.25, 0.0, 1.0)
    poses[:, 9:] = lower + (upper - lower) * np.clip(curl + rng.normal(0, 0.02, (n, 16)), 0, 1)
    return poses


def write_store(directory: Path, objects: list[str], seed: int = 0, pose_column_type=None) -> Path:
    """A pose store in the data engine's layout (with extra columns the reader ignores)."""
    rng = np.random.default_rng(seed)
    rows = {"object_id": [], "hand": [], "pose": [], "yaw_rad": [], "pose_index": [], "success": []}
    for object_id in objects:
        for yaw in YAWS:
            poses = synthetic_poses(object_id, yaw, POSES_PER_FRAME, rng)
            rows["object_id"] += [object_id] * len(poses)
            rows["hand"] += [HAND] * len(poses)
            rows["pose"] += [p.tolist() for p in poses]
            rows["yaw_rad"] += [yaw] * len(poses)
            rows["pose_index"] += [None] * len(poses)
            rows["success"] += [True] * len(poses)
    table = pa.table({
        "object_id": pa.array(rows["object_id"], pa.string()), "hand": pa.array(rows["hand"], pa.string()),
        "pose": pa.array(rows["pose"], pose_column_type or pa.list_(pa.float32())),
        "yaw_rad": pa.array(rows["yaw_rad"], pa.float64()), "pose_index": pa.array(rows["pose_index"], pa.int32()),
        "success": pa.array(rows["success"]),
    })
    return write_pose_store(directory, table)


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    return write_store(tmp_path_factory.mktemp("store"), synthetic_objects())


@pytest.fixture(scope="module")
def trained(store, tmp_path_factory):
    out = tmp_path_factory.mktemp("ckpt") / "allegro.pt"
    return train(store, HAND, out, tiny_config(), quiet())


@pytest.fixture(scope="module")
def sampler(trained):
    with PoseSampler(trained.checkpoint_path) as pose_sampler:
        yield pose_sampler


# ----------------------------------------------------------------------------- dataset
def test_reader_groups_poses_by_placement_and_splits_by_object(store):
    dataset = load_pose_dataset(store, HAND)
    objects = synthetic_objects()
    assert len(dataset) == len(objects) * len(YAWS) * POSES_PER_FRAME
    assert dataset.objects() == sorted(objects)
    assert len(dataset.frames) == len(objects) * len(YAWS)
    assert {f.pose_index for f in dataset.frames} == {-1}  # null pose_index -> the default resting pose
    train_ids, val_ids = split_objects(dataset.objects(), 0.2, seed=0)
    assert set(train_ids).isdisjoint(val_ids) and sorted(train_ids + val_ids) == sorted(objects) and len(val_ids) == 1
    assert split_objects(list(reversed(dataset.objects())), 0.2, seed=0) == (train_ids, val_ids)
    assert len(choose_fraction(train_ids, 0.4, seed=0)) == 2


def test_a_frame_whose_resting_pose_this_machine_lacks_is_left_out_with_a_warning(tmp_path):
    """A store built on another machine names resting pose 40 of an object that has fewer here: its poses
    are left out (never placed otherwise), the warning names the frame, and the dataset records it."""
    import pyarrow.compute as pc

    objects = synthetic_objects()[:2]
    source = write_store(tmp_path / "src", objects)
    table = pa.concat_tables([pq.read_table(p) for p in sorted((source / "shards").glob("*.parquet"))])
    moved = pc.and_(pc.equal(table.column("object_id"), objects[0]), pc.equal(table.column("yaw_rad"), YAWS[0]))
    pose_index = pc.if_else(moved, pa.scalar(40, pa.int32()), table.column("pose_index"))
    table = table.set_column(table.schema.get_field_index("pose_index"), "pose_index", pose_index)
    store = write_pose_store(tmp_path / "store", table)
    with pytest.warns(UserWarning, match=f"1 frame\\(s\\) left out.*{objects[0]} resting pose 40 \\({POSES_PER_FRAME} poses\\)"):
        dataset = load_pose_dataset(store, HAND)
    assert len(dataset) == (len(objects) * len(YAWS) - 1) * POSES_PER_FRAME
    assert all(f.pose_index == -1 for f in dataset.frames) and dataset.objects() == sorted(objects)
    assert dataset.skipped_summary() == [{"object_id": objects[0], "pose_index": 40, "yaw_rad": YAWS[0],
                                          "poses": POSES_PER_FRAME}]
    assert dataset.subset({objects[1]}).skipped == []


def test_reader_rejects_bad_stores(tmp_path):
    with pytest.raises(DatasetError, match="no such dataset"):
        load_pose_dataset(tmp_path / "missing", HAND)
    bare = tmp_path / "bare"  # Parquet files without the store's manifest are not a store
    bare.mkdir()
    pq.write_table(pa.table({"object_id": ["proc-box-004"], "hand": [HAND], "pose": [[0.0] * 25]}), bare / "a.parquet")
    with pytest.raises(DatasetError, match="not a pose store"):
        load_pose_dataset(bare, HAND)
    bad = write_pose_store(tmp_path / "short", pa.table({"object_id": ["proc-box-004"], "hand": [HAND],
                                                         "pose": [[0.0] * 24]}))
    with pytest.raises(DatasetError, match="25 floats"):
        load_pose_dataset(bad, HAND)
    tampered = write_store(tmp_path / "tampered", synthetic_objects()[:1])
    shard = next((tampered / "shards").glob("*.parquet"))
    shard.write_bytes(shard.read_bytes()[:-8] + b"\0" * 8)  # modified after the build
    with pytest.raises(DatasetError, match="differs from the manifest"):
        load_pose_dataset(tampered, HAND)
    with pytest.raises(DatasetError, match="no poses for hand 'leap'"):
        load_pose_dataset(write_store(tmp_path / "ok", synthetic_objects()[:1]), "leap")
    test_object = next(i for i in list_object_ids("test") if i.startswith("proc-box-"))
    leaked = write_pose_store(tmp_path / "leaked", pa.table({"object_id": [test_object], "hand": [HAND],
                                                             "pose": [[0.0] * 25]}))
    with pytest.raises(DatasetError, match="test objects are never used for training"):
        load_pose_dataset(leaked, HAND)


# ----------------------------------------------------------------------------- training
def test_training_loss_falls_and_writes_checkpoint_plot_and_manifest(trained):
    curve = [loss for _, loss in trained.history["train"]]
    assert trained.step == 300 and not trained.stopped
    assert curve[-1] < 0.5 * curve[0], curve
    assert trained.final_val_loss is not None and np.isfinite(trained.final_val_loss)
    assert trained.plot_path.stat().st_size > 1000
    manifest = json.loads(manifest_path(trained.checkpoint_path).read_text())
    assert manifest["dataset"]["sha256"] and manifest["dataset"]["val_objects"] == 1
    assert manifest["final_train_loss"] == pytest.approx(trained.final_train_loss)
    assert manifest.pop("sha256") == file_sha256(trained.checkpoint_path)  # the file the manifest describes
    assert load_checkpoint(trained.checkpoint_path).manifest == manifest


def test_interrupted_training_resumes_from_its_step_and_matches_an_uninterrupted_run(store, tmp_path):
    config = tiny_config(steps=120)
    first = train(store, HAND, tmp_path / "a.pt", config, quiet(should_stop=lambda step: step >= 60))
    assert first.stopped and first.step == 60 and first.checkpoint_path is None and first.state_path.is_file()
    resumed = train(store, HAND, tmp_path / "a.pt", config, quiet())
    assert resumed.start_step == 60 and resumed.step == 120 and not resumed.stopped
    straight = train(store, HAND, tmp_path / "b.pt", config, quiet(snapshot_every=50))
    a, b = load_checkpoint(resumed.checkpoint_path).state_dict, load_checkpoint(straight.checkpoint_path).state_dict
    assert all(torch.equal(a[name], b[name]) for name in a)  # snapshots (run b) change nothing either
    assert resumed.history == straight.history
    snapshots = sorted(tmp_path.glob("b.step*.pt"))
    assert [p.name for p in snapshots] == ["b.step100.pt", "b.step50.pt"]
    assert load_checkpoint(snapshots[1]).manifest["steps"] == 50
    with pytest.raises(TrainingError, match="different settings"):
        train(store, HAND, tmp_path / "a.pt", tiny_config(steps=120, lr=5e-4), quiet())


def test_object_balanced_batches_draw_every_object_equally_often_and_resume_only_with_the_same_balance(store, tmp_path):
    """An object with three times the poses of another is drawn as often as it under --balance objects."""
    object_ids = np.array(["many"] * 300 + ["few"] * 100, dtype=object)
    data = TrainingTensors(torch.zeros(400, 25), torch.zeros(400, dtype=torch.long), torch.zeros(1, 8),
                 object_balanced_weights(object_ids))
    rows = data.draw(20_000, torch.Generator().manual_seed(0)).numpy()
    assert abs((rows >= 300).mean() - 0.5) < 0.02  # uniform over poses would give 0.25
    assert len(np.unique(rows[rows >= 300])) == 100 and len(np.unique(rows[rows < 300])) == 300  # every pose still drawn
    first = train(store, HAND, tmp_path / "a.pt", tiny_config(steps=40), quiet(should_stop=lambda step: step >= 20))
    assert first.stopped
    with pytest.raises(TrainingError, match="different settings"):
        train(store, HAND, tmp_path / "a.pt", dataclasses.replace(tiny_config(steps=40), balance="objects"), quiet())
    balanced = train(store, HAND, tmp_path / "b.pt", dataclasses.replace(tiny_config(steps=40), balance="objects"), quiet())
    assert load_checkpoint(balanced.checkpoint_path).manifest["config"]["balance"] == "objects"
    with pytest.raises(TrainingError, match="--balance"):
        train(store, HAND, tmp_path / "c.pt", dataclasses.replace(tiny_config(steps=40), balance="families"), quiet())


# ----------------------------------------------------------------------------- sampling
@pytest.mark.parametrize("kind", ["ddpm", "ddim"])
def test_samplers_return_finite_poses_with_exact_rotations_and_legal_joints(sampler, kind):
    result = sampler.sample(synthetic_objects()[0], k=50, sampler=kind, seed=3)
    poses = result.poses_d
    assert poses.shape == (50, 25) and np.isfinite(poses).all()
    assert result.steps == (TRAIN_TIMESTEPS if kind == "ddpm" else 10)
    rotation = r6_to_matrix(poses[:, ROTATION_6D])
    np.testing.assert_allclose(rotation[..., :, :2].transpose(0, 2, 1).reshape(-1, 6), poses[:, ROTATION_6D], atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rotation), 1.0, atol=1e-9)
    lower, upper = hand_joint_limits(HAND)
    assert (poses[:, JOINTS] >= lower.numpy() - 1e-9).all() and (poses[:, JOINTS] <= upper.numpy() + 1e-9).all()


def test_samples_follow_the_geometry_they_were_trained_on(sampler):
    """The hand stands behind the object: at its back face, about half its height up."""
    for object_id in synthetic_objects()[:2]:
        points = frame_points(Frame(object_id, -1, 0.0))
        poses = sampler.sample(object_id, k=100, sampler="ddim", seed=0).poses_d
        assert np.median(poses[:, 0]) < points[:, 0].min() + 0.02
        assert abs(np.median(poses[:, 2]) - 0.5 * points[:, 2].max()) < 0.04


def test_sampling_is_deterministic_for_a_seed_and_varies_across_seeds(sampler):
    object_id = synthetic_objects()[1]
    a = sampler.sample(object_id, k=20, seed=7).poses_d
    b = sampler.sample(object_id, k=20, seed=7).poses_d
    c = sampler.sample(object_id, k=20, seed=8).poses_d
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


@pytest.mark.parametrize("kind", ["ddpm", "ddim"])
def test_a_lower_noise_scale_concentrates_the_samples_and_a_bad_one_is_refused(sampler, kind, monkeypatch):
    """The sampling temperature: scale 1 is the plain sampler; below 1 the same seed's poses spread less."""
    object_id = synthetic_objects()[0]
    plain = sampler.sample(object_id, k=200, sampler=kind, seed=5).poses_d
    np.testing.assert_array_equal(sampler.sample(object_id, k=200, sampler=kind, seed=5, noise_scale=1.0).poses_d, plain)
    cold = sampler.sample(object_id, k=200, sampler=kind, seed=5, noise_scale=0.3).poses_d
    assert np.isfinite(cold).all()
    assert cold[:, :3].std(axis=0).sum() < 0.8 * plain[:, :3].std(axis=0).sum()
    for bad in (0.0, -0.5, 1.5):
        with pytest.raises(SamplerInputError, match="noise scale"):
            sampler.sample(object_id, k=10, sampler=kind, noise_scale=bad)
    monkeypatch.setenv("GD2P_SAMPLER_NOISE_SCALE", "0.3")  # the default of requests that name none
    np.testing.assert_array_equal(sampler.sample(object_id, k=200, sampler=kind, seed=5).poses_d, cold)
    monkeypatch.setenv("GD2P_SAMPLER_NOISE_SCALE", "warm")
    with pytest.raises(SamplerInputError, match="GD2P_SAMPLER_NOISE_SCALE"):
        sampler.sample(object_id, k=10, sampler=kind)


def test_a_model_trained_with_condition_dropout_samples_with_guidance_and_a_plain_one_refuses_it(store, sampler, trained,
                                                                                                 tmp_path):
    """Classifier-free guidance: the weight travels in the shipped checkpoint; the same finished run re-ships
    its weights with another weight; guidance needs the unconditional embedding and a weight in [1, 10]."""
    unconditional = dataclasses.replace(TINY_MODEL, unconditional=True)
    config = tiny_config(model=unconditional, condition_dropout=0.2)
    guided_run = train(store, HAND, tmp_path / "guided.pt", config, quiet(guidance_scale=3.0))
    shutil.copy(guided_run.state_path, tmp_path / "plain.pt.train.pt")  # the finished run, shipped again with weight 1
    plain_run = train(store, HAND, tmp_path / "plain.pt", config, quiet())
    assert plain_run.start_step == plain_run.step == 300  # nothing retrained
    guided, plain = load_checkpoint(guided_run.checkpoint_path), load_checkpoint(plain_run.checkpoint_path)
    assert guided.guidance_scale == 3.0 and plain.guidance_scale == 1.0 and guided.model_config.unconditional
    assert all(torch.equal(guided.state_dict[k], plain.state_dict[k]) for k in guided.state_dict)
    object_id = synthetic_objects()[0]
    points = frame_points(Frame(object_id, -1, 0.0))
    with PoseSampler(guided_run.checkpoint_path) as guided_sampler, PoseSampler(plain_run.checkpoint_path) as plain_sampler:
        with_guidance = guided_sampler.sample(object_id, k=100, sampler="ddim", seed=0).poses_d
        without = plain_sampler.sample(object_id, k=100, sampler="ddim", seed=0).poses_d
    assert np.isfinite(with_guidance).all() and not np.allclose(with_guidance, without)
    assert np.median(with_guidance[:, 0]) < points[:, 0].min() + 0.02  # still behind the object
    with pytest.raises(TrainingError, match="unconditional"):
        train(store, HAND, tmp_path / "a.pt", tiny_config(condition_dropout=0.2), quiet())
    with pytest.raises(TrainingError, match="condition dropout"):
        train(store, HAND, tmp_path / "b.pt", tiny_config(), quiet(guidance_scale=2.0))
    with pytest.raises(TrainingError, match="guidance scale must be in"):
        train(store, HAND, tmp_path / "c.pt", config, quiet(guidance_scale=0.5))
    plain_model = load_checkpoint(trained.checkpoint_path)
    plain_model.guidance_scale = 2.0
    with pytest.raises(DiffusionConfigError, match="condition dropout"):
        PoseSampler(plain_model)


def write_store_with_failures(directory: Path, objects: list[str]) -> Path:
    """Per frame, successes half on the left (y = -4 cm) and half on the right of the object (+4 cm); failures,
    as many, all on the right: the right side is where pushes of these objects fail."""
    rng = np.random.default_rng(0)
    tables = []
    for object_id in objects:
        for yaw in YAWS:
            poses = synthetic_poses(object_id, yaw, 3 * POSES_PER_FRAME, rng)
            side = np.repeat([-0.04, 0.04, 0.04], POSES_PER_FRAME)
            poses[:, 1] += side
            success = np.repeat([True, True, False], POSES_PER_FRAME)
            tables.append(pa.table({
                "object_id": pa.array([object_id] * len(poses), pa.string()), "hand": pa.array([HAND] * len(poses), pa.string()),
                "pose": pa.array([p.tolist() for p in poses], pa.list_(pa.float32())),
                "yaw_rad": pa.array([yaw] * len(poses), pa.float64()), "pose_index": pa.nulls(len(poses), pa.int32()),
                "success": pa.array(success)}))
    return write_pose_store(directory, pa.concat_tables(tables))


def test_a_model_that_learns_failures_samples_guided_away_from_them(tmp_path):
    """--learn-failures: training reads the failed pushes too, under the failure embedding; guidance then moves
    the samples off the side where this object's pushes failed, without guidance they stay on both sides."""
    objects = synthetic_objects()[:3]
    store = write_store_with_failures(tmp_path / "store", objects)
    assert len(load_pose_dataset(store, HAND)) == 3 * 2 * 2 * POSES_PER_FRAME  # the successes only
    with_failures = load_pose_dataset(store, HAND, with_failures=True)
    assert len(with_failures) == 3 * 2 * 3 * POSES_PER_FRAME and int(with_failures.failed.sum()) == 3 * 2 * POSES_PER_FRAME
    assert np.all(with_failures.poses[with_failures.failed, 1] > 0.0)
    config = tiny_config(model=dataclasses.replace(TINY_MODEL, outcome=True), steps=1500, val_fraction=0.0)
    guided_run = train(store, HAND, tmp_path / "guided.pt", config, quiet(guidance_scale=4.0))
    shutil.copy(guided_run.state_path, tmp_path / "plain.pt.train.pt")
    plain_run = train(store, HAND, tmp_path / "plain.pt", config, quiet())
    assert load_checkpoint(guided_run.checkpoint_path).manifest["dataset"]["failed_poses_trained"] == 3 * 2 * POSES_PER_FRAME
    lateral = {}
    for name, run in (("guided", guided_run), ("plain", plain_run)):
        with PoseSampler(run.checkpoint_path) as pose_sampler:
            lateral[name] = np.concatenate([pose_sampler.sample(o, k=100, sampler="ddpm", seed=0).poses_d[:, 1] for o in objects])
    left = {name: float(np.mean(y < 0.0)) for name, y in lateral.items()}
    assert 0.3 < left["plain"] < 0.7, left  # both sides, as the successes
    assert left["guided"] > left["plain"] + 0.2, left  # away from the failures
    with pytest.raises(ValueError, match="not both"):
        dataclasses.replace(TINY_MODEL, outcome=True, unconditional=True)


def test_gradient_guidance_steers_the_last_steps_of_the_guided_requests_only(sampler):
    """A guide pulling the palm's x to the top of its range moves the guided samples there; a request batched
    beside them without a guide draws what it draws alone."""
    def toward_target(normalized: torch.Tensor) -> torch.Tensor:
        gradient = torch.zeros_like(normalized)
        gradient[:, 0] = 0.9 - normalized[:, 0]  # the gradient of -(x_0 - 0.9)^2 / 2
        return gradient

    bps = torch.as_tensor(np.stack([sampler.encode(o)[0] for o in synthetic_objects()[:2]]))
    generators = lambda: [torch.Generator().manual_seed(s) for s in (3, 4)]  # noqa: E731
    plain = sample_normalized(sampler.model, bps, [100, 100], generators())
    guided = sample_normalized(sampler.model, bps, [100, 100], generators(), guides=[toward_target, None],
                               gradient_guidance=GradientGuidance(scale=0.5, steps=20))
    assert float(guided[0][:, 0].mean()) > float(plain[0][:, 0].mean()) + 0.2
    assert (guided[0][:, 0] - 0.9).abs().median() < (plain[0][:, 0] - 0.9).abs().median() / 2
    torch.testing.assert_close(guided[1], plain[1], atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="one entry per request"):
        sample_normalized(sampler.model, bps, [10, 10], generators(), guides=[toward_target])
    for bad in ({"scale": 0.0}, {"scale": 0.1, "steps": 0}, {"scale": 0.1, "steps": TRAIN_TIMESTEPS + 1},
                {"scale": 0.1, "max_step": 0.0}):
        with pytest.raises(DiffusionConfigError):
            GradientGuidance(**bad)
    with pytest.raises(SamplerInputError, match="both a critic"):
        sampler.sample(synthetic_objects()[0], k=10, guidance=GradientGuidance(scale=0.1))


def test_concurrent_requests_are_batched_without_changing_their_samples(sampler):
    objects = synthetic_objects()[:4]
    alone = [sampler.sample(o, k=30, sampler="ddim", seed=i).poses_d for i, o in enumerate(objects)]
    together: dict[int, np.ndarray] = {}
    threads = [threading.Thread(target=lambda i=i, o=o: together.__setitem__(i, sampler.sample(o, k=30, sampler="ddim", seed=i).poses_d))
               for i, o in enumerate(objects)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    for i in range(len(objects)):
        np.testing.assert_allclose(together[i], alone[i], atol=1e-5)


def test_world_poses_follow_the_direction_frame(sampler):
    obj = load_object(synthetic_objects()[-1])  # a hull whose resting pose is not its mesh frame
    frame = default_frame(obj, direction_deg=90.0)
    frame = frame.model_copy(update={"object_pose": ObjectPose(position=(0.5, -0.2, frame.object_pose.position[2]),
                                                               quaternion_xyzw=frame.object_pose.quaternion_xyzw)})
    result = sampler.sample(obj, frame, k=10, seed=1)
    np.testing.assert_allclose(result.T_world_D[:3, 3], [0.5, -0.2, 0.0])
    np.testing.assert_allclose(result.poses_world, poses_d_to_world(result.poses_d, result.T_world_D))
    # the object turned with the push direction is the training placement at yaw -90 deg in D
    points_d, _, _ = sampler.points_in_d(obj, frame)
    expected = frame_points(Frame(obj.id, -1, -np.pi / 2))
    np.testing.assert_allclose(np.sort(points_d, axis=0), np.sort(expected, axis=0), atol=1e-9)
    assert object_yaw_in_d(frame, obj.default_pose.rotation) == pytest.approx(-np.pi / 2)


def test_checkpoint_round_trips_and_fp16_is_smaller(trained, tmp_path):
    checkpoint = load_checkpoint(trained.checkpoint_path)
    copy = save_checkpoint(checkpoint, tmp_path / "copy.pt")
    half = save_checkpoint(checkpoint, tmp_path / "half.pt", half=True)
    object_id = synthetic_objects()[2]
    with PoseSampler(checkpoint) as original, PoseSampler(copy) as reloaded, PoseSampler(half) as halved:
        a = original.sample(object_id, k=16, sampler="ddim", seed=5).poses_d
        np.testing.assert_array_equal(a, reloaded.sample(object_id, k=16, sampler="ddim", seed=5).poses_d)
        assert np.isfinite(halved.sample(object_id, k=16, sampler="ddim", seed=5).poses_d).all()
    assert half.stat().st_size < 0.7 * copy.stat().st_size
    np.testing.assert_array_equal(load_checkpoint(copy).bps.basis, checkpoint.bps.basis)
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError):
        load_checkpoint(tmp_path / "junk.pt")
    # A file swapped under its manifest (here: the fp16 weights where the fp32 ones were) is refused by name.
    copy.write_bytes(half.read_bytes())
    with pytest.raises(CheckpointError, match=r"copy\.pt: its SHA-256 .* its manifest copy\.pt\.manifest\.json records"):
        load_checkpoint(copy)


def test_objects_that_cannot_be_encoded_get_clear_errors(sampler, tmp_path):
    with pytest.raises(SamplerInputError, match="empty"):
        sampler.sample(np.zeros((0, 3)), k=4)
    huge = tmp_path / "huge_box.stl"
    trimesh.creation.box(extents=(1.0, 0.8, 0.5)).export(huge)
    with pytest.raises(SamplerInputError, match="beyond the BPS ball"):
        sampler.sample(str(huge), k=4)
    with pytest.raises(SamplerInputError, match="unknown object"):
        sampler.sample("no-such-object", k=4)
    with pytest.raises(SamplerInputError, match="k must be"):
        sampler.sample(synthetic_objects()[0], k=0)


# ----------------------------------------------------------------------------- nearest neighbour
def test_nearest_neighbor_returns_the_closest_training_frame_and_round_trips(store, tmp_path):
    dataset = load_pose_dataset(store, HAND)
    index = NearestNeighborBaseline.from_dataset(dataset)
    target = dataset.frames[3]
    match = index.query_points(frame_points(target), k=5, seed=0)
    assert match.frame == target and match.distance == pytest.approx(0.0, abs=1e-4)
    assert match.poses.shape == (5, 25)
    stored = dataset.poses[dataset.frame_index == 3]
    assert all(np.isclose(stored, pose, atol=1e-6).all(axis=1).any() for pose in match.poses)
    assert len(index.query_points(frame_points(target)).poses) == POSES_PER_FRAME
    reloaded = NearestNeighborBaseline.load(index.save(tmp_path / "nn.npz"))
    again = reloaded.query_points(frame_points(target), k=5, seed=0)
    assert again.frame == target
    np.testing.assert_array_equal(again.poses, match.poses)


# ----------------------------------------------------------------------------- service and CLI
def test_sample_request_over_the_bus(zenoh_router, trained, tmp_path, monkeypatch):
    # A hand whose checkpoint is missing (the shipped leap.pt is pointed away) gets a clear error reply.
    monkeypatch.setenv("GD2P_SAMPLER_CHECKPOINT_LEAP", str(tmp_path / "no-such-leap.pt"))
    from shared.bus import BusConfig, Dispatcher, RemoteError, Worker, open_session
    from shared.sampling.server import SERVICE, handlers

    session = open_session(BusConfig(connect=[zenoh_router], connect_timeout_ms=5000))
    stop = threading.Event()
    worker = Worker(SERVICE, handlers({HAND: trained.checkpoint_path}), worker_id="sampler-test", concurrency=4,
                    stop=stop, session=session, status_period_s=0.2)
    thread = threading.Thread(target=worker.run)
    thread.start()
    try:
        with Dispatcher(session, SERVICE, timeout_s=30) as dispatcher:
            dispatcher.wait_for_workers(1, timeout=20)
            frame = DirectionFrame(object_pose=ObjectPose(position=(0.4, 0.1, 0.05)), yaw_deg=180.0)
            request = SampleRequest(object=ObjectRef(library_id=synthetic_objects()[0]), hand=HAND, frame=frame, k=12,
                                    sampler="ddim", seed=2)
            reply = dispatcher.call(request, timeout=30)
            assert isinstance(reply, SampleResponse) and reply.request_id == request.id
            assert reply.poses_d.to_numpy().shape == (12, 25) and reply.checkpoint_id
            np.testing.assert_allclose(reply.poses_world.to_numpy()[:, :2].mean(0), [0.4, 0.1], atol=0.3)
            assert reply.noise_scale == 1.0  # no temperature asked, none set by $GD2P_SAMPLER_NOISE_SCALE
            cold = dispatcher.call(request.model_copy(update={"id": "cold", "noise_scale": 0.5}), timeout=30)
            assert cold.noise_scale == 0.5 and not np.allclose(cold.poses_d.to_numpy(), reply.poses_d.to_numpy())
            with pytest.raises(RemoteError, match="noise_scale"):
                dispatcher.call(request.model_copy(update={"id": "nn", "sampler": "nearest", "noise_scale": 0.5}), timeout=30)
            far_cloud = ObjectRef(point_cloud=np.full((5, 3), 3.0))
            with pytest.raises(RemoteError, match="bad_request"):
                dispatcher.call(request.model_copy(update={"id": "far", "object": far_cloud}), timeout=30)
            with pytest.raises(RemoteError, match="no usable leap checkpoint"):
                dispatcher.call(request.model_copy(update={"id": "leap", "hand": "leap"}), timeout=30)
    finally:
        stop.set()
        thread.join(15)
        session.close()


def test_cli_train_then_sample_json(store, tmp_path, capsys, monkeypatch):
    from cli.main import main

    out = tmp_path / "cli.pt"
    args = ["train", "--dataset", str(store), "--hand", HAND, "--out", str(out), "--steps", "30", "--warmup-steps", "5",
            "--batch-size", "32", "--hidden-dim", "64", "--num-blocks", "2", "--object-dim", "32", "--no-progress", "--json"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["step"] == 30 and Path(summary["checkpoint"]).is_file()
    monkeypatch.setenv("GD2P_SAMPLER_CHECKPOINT_ALLEGRO", str(out))
    assert main(["sample", "--object", synthetic_objects()[0], "--hand", HAND, "--n", "6", "--sampler", "ddim", "--json"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["n"] == 6 and len(report["poses"]) == 6 and len(report["poses"][0]["pose"]) == 25
    assert report["latency_s"] > 0 and "validated_success" not in report
    assert main(["sample", "--object", "no-such-object", "--hand", HAND, "--n", "2", "--json"]) == 2
    assert "unknown object" in capsys.readouterr().err
    assert main([*args[:-1], "--learn-failures", "--condition-dropout", "0.1"]) == 2  # one guidance base per model
    assert "do not combine" in capsys.readouterr().err


def test_cli_sample_validate_counts_successes_in_simulation(trained, capsys):
    pytest.importorskip("shared.validation.validator")
    from cli.main import main

    code = main(["sample", "--object", synthetic_objects()[0], "--hand", HAND, "--n", "3", "--sampler", "ddim",
                 "--checkpoint", str(trained.checkpoint_path), "--validate", "--json"])
    assert code == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert 0 <= report["validated_success"] <= 3
    assert report["validated_success"] == sum(p["success"] for p in report["poses"])


def test_cli_sample_with_critic_guidance_uses_the_hands_critic_only_for_its_own_checkpoint(trained, capsys):
    from cli.main import main

    base = ["sample", "--object", "proc-box-000", "--hand", HAND, "--n", "4", "--json"]
    assert main([*base, "--critic-guidance", "0.02", "--guided-steps", "2"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["critic_guidance"] == {"scale": 0.02, "steps": 2} and report["n"] == 4
    for extra, message in ((["--checkpoint", str(trained.checkpoint_path), "--critic-guidance", "0.02"], "made for the sampler checkpoint"),
                           (["--guided-steps", "3"], "--guided-steps needs --critic-guidance"),
                           (["--critic-guidance", "0.02", "--guided-steps", "500"], "guided steps must be in"),
                           (["--sampler", "nearest", "--critic-guidance", "0.02"], "apply to the diffusion samplers")):
        assert main([*base, *extra]) == 2, extra
        assert message in capsys.readouterr().err, extra


def test_denoiser_film_is_shared_across_a_requests_samples():
    """One FiLM row broadcast over a request gives the same output as one row per sample."""
    model = PoseDenoiser(TINY_MODEL).eval()
    x, bps = torch.randn(6, 25), torch.rand(1, 4096) * 0.3
    with torch.no_grad():
        embedding = model.encode_object(bps)
        shared = model.denoise(x, model.film(embedding, torch.tensor(40)))
        per_row = model(x, torch.full((6,), 40), bps.expand(6, -1))
    torch.testing.assert_close(shared, per_row)

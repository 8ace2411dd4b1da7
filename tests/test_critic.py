"""Success critic (issue 17 item 4): ROC AUC, learning on labelled poses of held-out objects, its
checkpoint, the sampler service's scores and the planner's order of candidates."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from shared.contracts.messages import ObjectRef, PlannerOptions, PushRequest, SampleRequest
from shared.planning.candidates import Candidates
from shared.planning.stages import PipelineSettings, RequestState, priority
from shared.robots.hands import load_hand
from shared.sampling.checkpoint import checkpoint_id, default_checkpoint_path
from shared.sampling.critic import CriticConfig, SuccessCritic
from shared.sampling.critic_features import CONTACT_FEATURES, contact_features
from shared.sampling.critic_train import (
    CriticData,
    CriticError,
    CriticTraining,
    evaluate,
    load_critic,
    roc_auc,
    save_critic,
    train_critic,
)
from shared.sampling.diffusion import GradientGuidance, PoseNormalizer
from shared.sampling.guidance import CriticGuide

torch.set_num_threads(1)
TINY = CriticConfig(bps_dim=32, object_dim=16, hidden_dim=64, num_layers=2, contact_dim=3)


def test_roc_auc_is_the_fraction_of_success_failure_pairs_ranked_right():
    assert roc_auc(np.array([0.1, 0.4, 0.35, 0.8]), np.array([0, 0, 1, 1])) == pytest.approx(0.75)
    assert roc_auc(np.array([2.0, 1.0]), np.array([0, 1])) == 0.0  # every pair ranked wrong
    assert roc_auc(np.array([0.5, 0.5]), np.array([0, 1])) == 0.5  # a tie counts half
    assert math.isnan(roc_auc(np.array([0.1, 0.2]), np.array([1, 1])))


def synthetic_data(objects: int, seed: int) -> CriticData:
    """Objects with random BPS; a pose succeeds when its x plus the object's first BPS feature plus its first
    contact feature is positive, so the critic must use the pose, the geometry and where they meet."""
    rng = np.random.default_rng(seed)
    bps = rng.normal(size=(objects, TINY.bps_dim)).astype(np.float32)
    group = np.repeat(np.arange(objects), 40)
    poses = rng.normal(size=(len(group), 25)).astype(np.float32)
    contact = rng.normal(size=(len(group), TINY.contact_dim)).astype(np.float32)
    success = (poses[:, 0] + bps[group, 0] + contact[:, 0] > 0).astype(np.float32)
    error = np.where(success > 0, 0.01, 0.1).astype(np.float32)
    return CriticData(torch.as_tensor(poses), torch.as_tensor(group), torch.as_tensor(bps), torch.as_tensor(success),
                      torch.as_tensor(error), [f"obj-{i}" for i in range(objects)], torch.as_tensor(contact))


@pytest.fixture(scope="module")
def trained():
    settings = CriticTraining(steps=400, batch_size=128, eval_every=100, config=TINY)
    return train_critic(synthetic_data(30, seed=0), synthetic_data(8, seed=1), settings)


def test_the_critic_learns_which_poses_succeed_on_objects_it_never_saw(trained):
    model, result = trained
    metrics = evaluate(model, synthetic_data(8, seed=2))
    assert metrics["roc_auc"] > 0.9, metrics
    assert metrics["top6_success"] > metrics["all_success"] + 0.3, metrics  # its favourite poses push well
    assert result["best_step"] in [h["step"] for h in result["history"]]


def test_a_critic_round_trips_through_its_checkpoint(trained, tmp_path):
    model, _ = trained
    path = save_critic(model, tmp_path / "critic.pt", "allegro", "sampler-abc", {"note": "test"})
    loaded = load_critic(path)
    data = synthetic_data(2, seed=3)
    assert loaded.hand == "allegro" and loaded.sampler_checkpoint_id == "sampler-abc"
    assert torch.allclose(loaded.model(data.poses, data.bps, data.group, data.contact)[0],
                          model(data.poses, data.bps, data.group, data.contact)[0])
    with pytest.raises(ValueError, match="contact features"):
        loaded.model(data.poses, data.bps, data.group)  # a critic trained with contact features cannot score without
    assert (tmp_path / "critic.pt.manifest.json").is_file()
    torch.save({"format": "something else"}, tmp_path / "other.pt")
    with pytest.raises(CriticError, match="not a gd2p-critic"):
        load_critic(tmp_path / "other.pt")


def test_contact_features_say_where_the_hand_meets_the_object():
    hand = load_hand("allegro")
    pose = hand.open_pose(1)
    pose[0, :3] = torch.tensor([-0.12, 0.0, 0.08])
    touched = hand.contact_candidates_world(hand.forward(pose))[0][0, 0]  # a point on the hand's surface
    rng = np.random.default_rng(0)
    near = touched + torch.as_tensor(rng.normal(scale=0.001, size=(200, 3)), dtype=torch.float32)
    far = torch.tensor([0.5, 0.5, 0.3]) + torch.as_tensor(rng.normal(scale=0.01, size=(200, 3)), dtype=torch.float32)
    features = contact_features(hand, pose, torch.cat([near, far]))[0]
    assert features.shape == (CONTACT_FEATURES,)
    centroid, closest, share_1cm = features[:3], features[3], features[4]
    assert torch.linalg.norm(centroid - touched) < 0.003  # the push acts where the hand touches, not at the far points
    assert abs(float(closest)) < 0.005 and 0.45 < float(share_1cm) < 0.55  # half the points are at the hand
    assert torch.allclose(features[13:16], torch.cat([near, far]).min(0).values, atol=0.05)  # the object's extent
    moved_away = contact_features(hand, pose, torch.cat([near, far]) + torch.tensor([0.0, 0.0, 1.0]))[0]
    assert float(moved_away[3]) > 0.5 and float(moved_away[4]) == 0.0  # nothing within a centimetre
    with pytest.raises(ValueError, match="object points"):
        contact_features(hand, pose, torch.zeros(0, 3))


def test_critic_guidance_climbs_the_critics_success_probability_from_inside_the_samplers_inference_mode():
    torch.manual_seed(0)
    hand = load_hand("allegro")
    critic = SuccessCritic(CriticConfig(bps_dim=32, contact_dim=CONTACT_FEATURES)).eval()
    rng = np.random.default_rng(0)
    box = rng.uniform([-0.03, -0.03, 0.0], [0.03, 0.03, 0.08], size=(600, 3))
    normalizer = PoseNormalizer(torch.full((25,), -2.0), torch.full((25,), 2.0))  # wide: no pose is clamped
    guide = CriticGuide(critic, hand, rng.normal(size=32), box, normalizer)
    poses = hand.open_pose(16)
    poses[:, :3] = torch.as_tensor(rng.uniform([-0.12, -0.03, 0.02], [-0.06, 0.03, 0.08], size=(16, 3)), dtype=torch.float32)

    @torch.no_grad()
    def log_success(normalized: torch.Tensor) -> torch.Tensor:
        raw = normalizer.unnormalize(normalized)
        logits, _ = critic(raw, guide.bps, None, contact_features(hand, raw, guide.points))
        return torch.nn.functional.logsigmoid(logits)

    start = normalizer.normalize(poses)
    with torch.inference_mode():  # where the sampler calls it
        climbed = GradientGuidance(scale=0.05, max_step=0.05).move(start, guide)
    assert climbed.shape == start.shape
    assert float(log_success(climbed).sum()) > float(log_success(start).sum())
    assert ((climbed - start).norm(dim=1) <= 0.05 + 1e-6).all()  # no pose moves further than the cap


@pytest.mark.parametrize("contact_dim", [0, CONTACT_FEATURES])  # 0: critics trained before contact features
def test_the_sampler_scores_its_samples_only_with_a_critic_made_for_its_checkpoint(tmp_path, monkeypatch, contact_dim):
    from shared.sampling.server import SamplerService

    shipped = default_checkpoint_path("allegro")
    if not shipped.is_file():
        pytest.skip("no shipped Allegro checkpoint")
    service = SamplerService()
    request = SampleRequest(object=ObjectRef(library_id="proc-box-000"), hand="allegro", k=20,
                            frame=_frame_at_origin())
    critic = SuccessCritic(CriticConfig(bps_dim=service.sampler("allegro").bps.n, contact_dim=contact_dim))
    matching = save_critic(critic, tmp_path / "matching.pt", "allegro", checkpoint_id(shipped), {})
    other = save_critic(critic, tmp_path / "other.pt", "allegro", "another-checkpoint", {})
    try:
        monkeypatch.setenv("GD2P_CRITIC_CHECKPOINT_ALLEGRO", str(matching))
        scores = service.handle(request).success_probability.to_numpy()
        assert scores.shape == (20,) and ((scores > 0) & (scores < 1)).all()
        assert service.handle(request.model_copy(update={"score": False})).success_probability is None  # not asked
    finally:
        service.close()
    service = SamplerService()
    try:
        monkeypatch.setenv("GD2P_CRITIC_CHECKPOINT_ALLEGRO", str(other))
        assert service.handle(request).success_probability is None
    finally:
        service.close()


def test_the_sampler_service_guides_samples_with_its_critic_when_asked_and_refuses_when_it_cannot(monkeypatch):
    from shared.contracts.errors import ServiceError
    from shared.sampling.server import SamplerService

    request = SampleRequest(object=ObjectRef(library_id="proc-box-000"), hand="allegro", k=40, frame=_frame_at_origin(),
                            seed=3)
    service = SamplerService()
    try:
        plain = service.handle(request).success_probability.to_numpy()
        guided = service.handle(request.model_copy(update={"critic_guidance": 0.02, "guided_steps": 5}))
        assert guided.success_probability.to_numpy().mean() > plain.mean() + 0.02  # the shipped critic's own view
        with pytest.raises(ServiceError, match="apply to the diffusion samplers"):
            service.handle(request.model_copy(update={"sampler": "nearest", "critic_guidance": 0.02}))
    finally:
        service.close()
    monkeypatch.setenv("GD2P_CRITIC_CHECKPOINT_ALLEGRO", "none")
    service = SamplerService()
    try:
        with pytest.raises(ServiceError, match="critic guidance needs"):
            service.handle(request.model_copy(update={"critic_guidance": 0.02}))
    finally:
        service.close()


def test_retrieved_poses_are_scored_by_the_same_critic_so_a_planner_orders_them_alike(monkeypatch):
    """The Nearest Neighbor baseline gets the critic's order too (PlannerOptions.critic), scored from the object as the
    diffusion sampler encodes it, the encoding the critic was trained on."""
    from shared.sampling.critic_train import success_probabilities
    from shared.sampling.server import SamplerService, object_input

    request = SampleRequest(object=ObjectRef(library_id="proc-box-000"), hand="allegro", k=30, frame=_frame_at_origin(),
                            sampler="nearest", seed=2)
    service = SamplerService()
    try:
        reply = service.handle(request)
        poses = reply.poses_d.to_numpy()
        sampler = service.sampler("allegro")
        points_d, _, label = sampler.points_in_d(object_input(request.object), request.frame)
        expected = success_probabilities(service.critic("allegro", sampler), "allegro",
                                         sampler.encode_points(points_d, label), points_d, poses)
        np.testing.assert_allclose(reply.success_probability.to_numpy(), expected, rtol=1e-6)
        assert np.ptp(expected) > 0.05  # the scores tell the retrieved poses apart
        assert service.handle(request.model_copy(update={"score": False})).success_probability is None
    finally:
        service.close()
    monkeypatch.setenv("GD2P_CRITIC_CHECKPOINT_ALLEGRO", "none")
    service = SamplerService()
    try:
        assert service.handle(request).success_probability is None  # no critic: retrieval's own order
    finally:
        service.close()


def _frame_at_origin():
    from shared.contracts.messages import DirectionFrame, ObjectPose

    return DirectionFrame(object_pose=ObjectPose(position=(0.55, 0.0, 0.05), quaternion_xyzw=(0.0, 0.0, 0.0, 1.0)),
                          yaw_deg=0.0)


def test_the_planner_tries_the_poses_the_critic_likes_best_first():
    hand = load_hand("allegro")
    poses = np.zeros((4, 25))
    candidates = Candidates(poses, poses, np.repeat(np.eye(4)[None], 4, axis=0), np.zeros((4, 16)),
                            l_dir=np.array([0.1, 0.2, 0.3, 0.4]), p_success=np.array([0.2, 0.9, 0.9, 0.1]))

    def state(**asks: bool) -> RequestState:
        request = PushRequest(object=ObjectRef(library_id="proc-box-000"), direction_deg=0.0, options=PlannerOptions(**asks))
        return RequestState(request, None, "", hand, np.eye(4))

    assert priority(state(), candidates).tolist() == [1, 2, 0, 3]  # the default: the critic, L_dir breaks the tie
    assert priority(state(critic=False), candidates).tolist() == [0, 1, 2, 3]  # L_dir alone
    assert PipelineSettings().for_push(state().request).prescreen == 24  # the critic's order keeps the prescreen
    assert PipelineSettings().for_push(state(prescreen=False).request).prescreen == 0  # the fast path


@pytest.mark.parametrize("hand", ["allegro", "leap"])
def test_each_hand_ships_a_critic_for_its_default_sampler(hand, monkeypatch):
    # The sampler service ignores a critic made for another checkpoint: a retrained default without its
    # critic retrained would silently lose the fast path's order (CHANGELOG.md "The success critic").
    from shared.sampling.critic_train import default_critic_path

    monkeypatch.delenv(f"GD2P_CRITIC_CHECKPOINT_{hand.upper()}", raising=False)
    monkeypatch.delenv(f"GD2P_SAMPLER_CHECKPOINT_{hand.upper()}", raising=False)
    path = default_critic_path(hand)
    assert path is not None and path.is_file(), f"no shipped {hand} critic"
    loaded = load_critic(path)
    assert loaded.hand == hand and loaded.sampler_checkpoint_id == checkpoint_id(default_checkpoint_path(hand))
    assert loaded.manifest["best_val"]["roc_auc"] > 0.7  # chosen on val objects, well above chance


def _write_records(directory, object_ids: list[str], sampler_id: str, seed: int) -> None:
    """Labelled records as `gd2p critic data` writes them (random poses near the object, random outcomes)."""
    import json

    rng = np.random.default_rng(seed)
    hand = load_hand("allegro")
    directory.mkdir()
    with (directory / "records.jsonl").open("w") as out:
        for object_id in object_ids:
            poses = hand.open_pose(16).numpy()
            poses[:, :3] = rng.uniform([-0.15, -0.05, 0.02], [-0.08, 0.05, 0.1], size=(16, 3))
            success = rng.random(16) < 0.5
            out.write(json.dumps({"key": f"allegro/{object_id}", "object_id": object_id, "hand": "allegro",
                                  "yaw_deg": float(rng.uniform(-180, 180)), "per_object": 16, "seed": seed,
                                  "checkpoint_id": sampler_id, "poses_d": poses.tolist(), "success": success.tolist(),
                                  "position_error_m": np.where(success, 0.01, 0.08).tolist()}) + "\n")


def test_critic_train_learns_from_several_data_directories_and_refuses_test_objects(tmp_path, capsys):
    import json

    from cli.main import main

    sampler_id = checkpoint_id(default_checkpoint_path("allegro"))
    _write_records(tmp_path / "train-a", ["proc-spatula-077", "rnd-957"], sampler_id, seed=0)
    _write_records(tmp_path / "train-b", ["proc-spatula-077"], sampler_id, seed=1)  # the same object at another yaw
    _write_records(tmp_path / "val", ["proc-bottle-076", "rnd-211"], sampler_id, seed=2)
    out = tmp_path / "critic.pt"
    assert main(["critic", "train", "--data", str(tmp_path / "train-a"), str(tmp_path / "train-b"),
                 "--val", str(tmp_path / "val"), "--steps", "20", "--out", str(out)]) == 0
    manifest = json.loads((tmp_path / "critic.pt.manifest.json").read_text())
    assert manifest["train_poses"] == 48 and manifest["train_objects"] == 2
    assert manifest["train_data"] == [str(tmp_path / "train-a"), str(tmp_path / "train-b")]
    assert load_critic(out).model.config.contact_dim == CONTACT_FEATURES
    assert main(["critic", "train", "--data", str(tmp_path / "train-a"), "--val", str(tmp_path / "val"), "--steps", "20",
                 "--no-contact", "--hidden-dim", "16", "--layers", "3", "--out", str(tmp_path / "plain.pt")]) == 0
    config = load_critic(tmp_path / "plain.pt").model.config
    assert (config.contact_dim, config.hidden_dim, config.num_layers, config.object_dim) == (0, 16, 3, 8)
    _write_records(tmp_path / "test", ["rnd-741"], sampler_id, seed=3)
    capsys.readouterr()
    assert main(["critic", "train", "--data", str(tmp_path / "train-a"), str(tmp_path / "test"),
                 "--val", str(tmp_path / "val"), "--out", str(tmp_path / "never.pt")]) == 2
    assert "test objects are for reporting only" in capsys.readouterr().err
    assert not (tmp_path / "never.pt").exists()


def test_a_capture_view_carries_the_same_pushes_into_the_reconstructions_frame(tmp_path):
    """Each record also comes as each of its reconstructed captures: the same outcomes, the poses moved by the
    capture's shift, BPS and contact features read from the captured points; a failed capture adds nothing."""
    from shared.sampling.capture_bps import FrameCaptures
    from shared.sampling.critic_train import critic_frame, critic_frames, encode_records
    from shared.sampling.sampling import PoseSampler
    from shared.world.perception.object_model import BPS_POINTS

    sampler_id = checkpoint_id(default_checkpoint_path("allegro"))
    _write_records(tmp_path / "data", ["proc-spatula-077", "rnd-957"], sampler_id, seed=0)
    from shared.sampling.critic_train import read_records

    records = read_records(tmp_path / "data")
    shift = np.array([0.004, -0.003], np.float32)
    with PoseSampler(default_checkpoint_path("allegro")) as sampler:
        # A stand-in capture of the first object: its mesh points seen from a frame `shift` away, exactly.
        mesh_points, _, _ = sampler.points_in_d("proc-spatula-077", critic_frame("proc-spatula-077", records[0]["yaw_deg"]))
        seen = (mesh_points + np.array([*shift, 0.0]))[:BPS_POINTS].astype(np.float32)
        points = np.zeros((2, 2, BPS_POINTS, 3), np.float32)
        points[0, 0, :len(seen)] = seen
        captures = FrameCaptures(critic_frames(records), bps=np.zeros((2, 2, 4), np.float32),
                                 shift_xy=np.tile(shift, (2, 2, 1)), ok=np.array([[True, False], [False, False]]),
                                 points_d=points, point_counts=np.array([[len(seen), 0], [0, 0]]))
        plain = encode_records(records, sampler)
        data = encode_records(records, sampler, captures=captures)
    assert plain.captured is None and len(plain.bps) == 2
    assert len(data.bps) == 3 and data.object_ids == ["proc-spatula-077", "proc-spatula-077", "rnd-957"]
    mesh, capture = data.group == 0, data.group == 1
    assert data.captured.tolist() == capture.tolist() and int(capture.sum()) == 16
    assert torch.equal(data.success[capture], data.success[mesh])  # the same physical pushes, the same outcomes
    assert torch.allclose(data.poses[capture][:, :2], data.poses[mesh][:, :2] + torch.as_tensor(shift))
    assert torch.equal(data.poses[capture][:, 2:], data.poses[mesh][:, 2:])
    # Hand and object moved together: the same distances, the contact centroid moved with them.
    assert torch.allclose(data.contact[capture][:, 3:6], data.contact[mesh][:, 3:6], atol=1e-5)
    assert torch.allclose(data.contact[capture][:, :2], data.contact[mesh][:, :2] + torch.as_tensor(shift), atol=1e-5)
    assert not torch.allclose(data.bps[1], data.bps[0])  # the BPS is read in the capture's frame


def test_a_capture_fraction_sets_each_batchs_share_of_capture_views():
    from shared.sampling.critic_train import _batch_rows

    data = synthetic_data(6, seed=0)
    captured = data.group >= 4  # two of the six views are captures
    data = CriticData(data.poses, data.group, data.bps, data.success, data.error_m, data.object_ids, data.contact, captured)
    generator = torch.Generator().manual_seed(0)
    rows = _batch_rows(data, CriticTraining(batch_size=100, capture_fraction=0.25), generator)()
    assert int(captured[rows].sum()) == 25 and len(rows) == 100
    rows = _batch_rows(data, CriticTraining(batch_size=100), generator)()  # 0: uniform over every row
    assert 10 < int(captured[rows].sum()) < 60
    metrics = evaluate(SuccessCritic(TINY), data)
    assert metrics["mesh"]["objects"] == 4 and metrics["captures"]["objects"] == 2


def test_critic_train_on_captures_builds_them_resumably_beside_the_data(tmp_path, capsys):
    import json

    from cli.main import main

    sampler_id = checkpoint_id(default_checkpoint_path("allegro"))
    _write_records(tmp_path / "train", ["proc-box-003"], sampler_id, seed=0)
    _write_records(tmp_path / "val", ["proc-bottle-076"], sampler_id, seed=2)
    assert main(["critic", "train", "--data", str(tmp_path / "train"), "--val", str(tmp_path / "val"), "--steps", "10",
                 "--capture-fraction", "0.5", "--workers", "1", "--out", str(tmp_path / "critic.pt")]) == 0
    manifest = json.loads((tmp_path / "critic.pt.manifest.json").read_text())
    assert manifest["settings"]["capture_fraction"] == 0.5
    assert manifest["captures"][str(tmp_path / "train")]["settings"]["cameras"] == 3  # what the captures were
    assert manifest["train_poses"] == 16 * 3  # the mesh view and both captures of the box
    assert set(manifest["best_val"]) >= {"mesh", "captures"}
    assert (tmp_path / "train" / "captures" / "settings.json").is_file()
    capsys.readouterr()
    assert main(["critic", "eval", "--data", str(tmp_path / "val"), "--critic", str(tmp_path / "critic.pt"),
                 "--captures", "--workers", "1"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["mesh"]["poses"] == 16 and report["captures"]["poses"] == 32
    with pytest.raises(SystemExit):
        main(["critic", "train", "--data", str(tmp_path / "train"), "--val", str(tmp_path / "val"),
              "--capture-fraction", "1.5", "--out", str(tmp_path / "never.pt")])
    assert "--capture-fraction: must be in [0, 1]" in capsys.readouterr().err

"""Push validation in PyBullet: outcomes a user relies on, augmentation bounds, service and CLI contracts."""
from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
import trimesh

from shared.bus import BusConfig, Worker, job_key, live_workers, open_session
from shared.bus.worker import timeout_attachment
from shared.contracts.codec import decode, encode
from shared.contracts.errors import ServiceError
from shared.contracts.messages import DirectionFrame, ErrorReply, ObjectRef, ValidationJob, ValidationResult
from shared.frames import make_transform, pose25_to_matrix
from shared.robots.hands import load_hand
from shared.validation.augment import MAX_JOINT_RAD, MAX_ROTATION_DEG, MAX_TRANSLATION_M, halton_perturbations
from shared.validation.jobs import validate
from shared.validation.push import PushSimulator, table_object
from shared.validation.validator import PLACEMENT_NOISE_XY_M, PLACEMENT_NOISE_YAW_DEG, placement_offsets
from shared.world.fixed_poses import SPATULA_GAP_M, spatula_pose
from shared.world.objects import load_object
from shared.world.push_outcome import object_pose

BOX_ID = "proc-box-001"  # 19 x 11 x 8 cm, 0.86 kg, volumetric


@pytest.fixture(scope="module")
def box():
    return table_object(load_object(BOX_ID))


@pytest.fixture(scope="module")
def tall_thin(tmp_path_factory):
    """A 4 x 8 x 25 cm slab standing on its 4 x 8 cm end (thin along the push direction)."""
    path = tmp_path_factory.mktemp("meshes") / "slab.stl"
    trimesh.creation.box((0.04, 0.08, 0.25)).export(path)
    obj = table_object(load_object(path))
    extent = obj.vertices_d.max(0) - obj.vertices_d.min(0)
    assert extent[0] == pytest.approx(0.04, abs=1e-6) and extent[2] == pytest.approx(0.25, abs=1e-6)
    return obj


@pytest.mark.parametrize("hand_name", ["allegro", "leap"])
def test_spatula_push_moves_box_to_goal(box, hand_name):
    hand = load_hand(hand_name)
    with PushSimulator(hand, box) as sim:
        outcome = sim.run(spatula_pose(hand, box.vertices_d))
    assert outcome.success, outcome
    assert outcome.position_error_m < 0.03 and outcome.rotation_deg < 45
    assert outcome.contact_kept and not outcome.hand_table_contact
    assert outcome.initial_penetration_m < 1e-3


@pytest.mark.parametrize("hand_name", ["allegro", "leap"])
def test_spatula_pose_faces_push_direction_behind_object(box, hand_name):
    hand = load_hand(hand_name)
    pose = spatula_pose(hand, box.vertices_d)
    base, _ = pose25_to_matrix(pose)
    palm_normal = base[:3, :3] @ hand.palm_normal_base.double().numpy()
    np.testing.assert_allclose(palm_normal, [1.0, 0.0, 0.0], atol=1e-9)
    with PushSimulator(hand, box) as sim:  # the gap as PyBullet sees it, before anything moves
        sim.hand.place(base, pose[9:])
        gap = sim.scene.closest_distance(sim.hand, sim.body, 0.05)
    assert 0.0 < gap <= SPATULA_GAP_M  # PyBullet's ~1 mm convex-hull margin on the object eats into it


def test_hand_on_far_side_pushing_away_fails(box):
    hand = load_hand("allegro")
    pose = spatula_pose(hand, box.vertices_d)
    depth = np.ptp(box.vertices_d[:, 0])
    pose[0] += depth + 0.10  # beyond the object's +x face, palm facing +x: moves away from it
    with PushSimulator(hand, box) as sim:
        outcome = sim.run(pose)
    assert not outcome.success
    assert outcome.position_error_m == pytest.approx(0.20, abs=0.01)  # the object stayed where it was
    assert outcome.contact_fraction == 0.0 and not outcome.contact_kept


def test_tall_thin_object_pushed_high_topples(tall_thin):
    hand = load_hand("allegro")
    pose = spatula_pose(hand, tall_thin.vertices_d)
    pose[2] += 0.20  # lowest palm contact 20 cm up a 25 cm slab, far above half-width / mu
    with PushSimulator(hand, tall_thin) as sim:
        outcome = sim.run(pose)
    assert not outcome.success
    assert outcome.max_tilt_deg > 45 and outcome.rotation_deg > 45


def test_service_results_are_deterministic_for_a_seed(box):
    hand = load_hand("allegro")
    spatula = spatula_pose(hand, box.vertices_d)
    far_side = spatula + np.r_[np.ptp(box.vertices_d[:, 0]) + 0.10, np.zeros(24)]
    job = ValidationJob(object=ObjectRef(library_id=BOX_ID), hand="allegro", poses=np.stack([spatula, far_side]),
                        augment=True, seed=7)
    first, second = validate(job), validate(job.model_copy(update={"id": "again"}))
    np.testing.assert_array_equal(first.success.to_numpy(), [True, False])
    for name in ("success", "position_error_m", "rotation_deg", "max_tilt_deg", "contact_kept"):
        np.testing.assert_array_equal(getattr(first, name).to_numpy(), getattr(second, name).to_numpy())
    assert first.augmented is not None and second.augmented is not None
    np.testing.assert_array_equal(first.augmented.parent_index.to_numpy(), [0] * 10)  # copies of the success only
    np.testing.assert_array_equal(first.augmented.poses.to_numpy(), second.augmented.poses.to_numpy())
    np.testing.assert_array_equal(first.augmented.position_error_m.to_numpy(), second.augmented.position_error_m.to_numpy())
    decoded = decode(*encode(first), ValidationResult)  # what a caller receives over the bus
    np.testing.assert_array_equal(decoded.augmented.success.to_numpy(), first.augmented.success.to_numpy())


def test_augmentation_stays_within_paper_bounds_and_is_deterministic():
    hand = load_hand("allegro")
    lower, upper = hand.joint_lower.double().numpy(), hand.joint_upper.double().numpy()
    rng = np.random.default_rng(0)
    pose = spatula_pose(hand, rng.uniform(-0.05, 0.05, (50, 3)) + [0, 0, 0.05])
    pose[9:] = np.clip(rng.uniform(lower, upper), lower + 0.06, upper - 0.06)  # interior: no clipping
    copies = halton_perturbations(pose, 200, seed=3, joint_lower=lower, joint_upper=upper)
    assert copies.shape == (200, 25)
    base, joints = pose25_to_matrix(pose)
    copy_bases, copy_joints = pose25_to_matrix(copies)
    shift = np.linalg.norm(copy_bases[:, :3, 3] - base[:3, 3], axis=1)
    relative = np.einsum("ji,njk->nik", base[:3, :3], copy_bases[:, :3, :3])
    angle = np.degrees(np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    joint_change = np.abs(copy_joints - joints)
    assert shift.max() <= MAX_TRANSLATION_M + 1e-12 and shift.max() > 0.8 * MAX_TRANSLATION_M
    assert angle.max() <= MAX_ROTATION_DEG + 1e-9 and angle.max() > 0.8 * MAX_ROTATION_DEG
    assert joint_change.max() <= MAX_JOINT_RAD + 1e-12 and joint_change.max() > 0.9 * MAX_JOINT_RAD
    np.testing.assert_array_equal(copies, halton_perturbations(pose, 200, seed=3, joint_lower=lower, joint_upper=upper))
    assert not np.array_equal(copies, halton_perturbations(pose, 200, seed=4, joint_lower=lower, joint_upper=upper))


def test_augmentation_clips_joints_to_limits():
    hand = load_hand("leap")
    lower, upper = hand.joint_lower.double().numpy(), hand.joint_upper.double().numpy()
    pose = spatula_pose(hand, np.array([[0.0, 0.0, 0.0], [0.05, 0.05, 0.1]]))
    pose[9:] = upper  # at the upper limit: half the noise would leave the range
    copies = halton_perturbations(pose, 10, seed=0, joint_lower=lower, joint_upper=upper)
    assert np.all(copies[:, 9:] <= upper) and np.all(copies[:, 9:] >= lower)


def test_service_rejects_what_it_cannot_simulate():
    poses = np.zeros((1, 25))
    poses[0, 3], poses[0, 7] = 1.0, 1.0
    cloud = ValidationJob(object=ObjectRef(point_cloud=np.zeros((10, 3))), hand="allegro", poses=poses)
    with pytest.raises(ServiceError) as info:
        validate(cloud)
    assert info.value.code == "bad_request" and "point cloud" in str(info.value)
    unknown = ValidationJob(object=ObjectRef(library_id="proc-nothing-000"), hand="allegro", poses=poses)
    with pytest.raises(ServiceError) as info:
        validate(unknown)
    assert info.value.code == "bad_request" and "proc-nothing-000" in str(info.value)


def test_cli_validate_prints_results_json(capsys):
    from cli.main import main

    code = main(["validate", "--object", BOX_ID, "--hand", "allegro", "--fixed-pose", "spatula", "--trials", "2",
                 "--seed", "5", "--json"])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert [r["trial"] for r in report["results"]] == [0, 1]
    first, second = report["results"]
    assert first["success"] is True and second["success"] is True
    assert first["position_error_m"] != second["position_error_m"]  # different placement noise
    for key in ("position_error_m", "rotation_deg", "max_tilt_deg", "contact_kept", "hand_table_contact",
                "initial_penetration_m"):
        assert key in first


def test_placement_noise_is_small_and_seeded():
    offsets = placement_offsets(50, seed=1)
    shift = np.linalg.norm(offsets[:, :2, 3], axis=1)
    yaw = np.degrees(np.abs(np.arctan2(offsets[:, 1, 0], offsets[:, 0, 0])))
    assert shift.max() <= PLACEMENT_NOISE_XY_M and yaw.max() <= PLACEMENT_NOISE_YAW_DEG
    np.testing.assert_array_equal(offsets[:10], placement_offsets(10, seed=1))  # more trials extend fewer
    assert not np.array_equal(offsets, placement_offsets(50, seed=2))


def test_cli_validate_reports_bad_poses_file(tmp_path, capsys):
    from cli.main import main

    bad = tmp_path / "poses.json"
    bad.write_text(json.dumps({"poses": [{"pose": [0.0] * 24}]}))
    code = main(["validate", "--object", BOX_ID, "--hand", "allegro", "--poses", str(bad), "--json"])
    assert code == 2
    captured = capsys.readouterr()
    assert captured.out == "" and 'poses[0]["pose"] must be 25' in captured.err


def test_floating_job_places_the_object_as_its_frame_says():
    """A job's DirectionFrame turns the object in D (the planner's pre-screen pushes in the request's frame)."""
    obj = load_object(BOX_ID)
    yaw = np.radians(90.0)
    turned = table_object(obj, None, yaw)
    hand = load_hand("allegro")
    pose = spatula_pose(hand, turned.vertices_d)
    T_world_O = make_transform(np.eye(3), np.array([0.5, 0.1, 0.0])) @ obj.T_D_O(None, yaw)
    frame = DirectionFrame(object_pose=object_pose(T_world_O), yaw_deg=0.0)
    framed = validate(ValidationJob(object=ObjectRef(library_id=BOX_ID), hand="allegro", poses=pose[None], frame=frame))
    with PushSimulator(hand, turned) as sim:
        expected = sim.run(pose)
    assert expected.success and bool(framed.success.to_numpy()[0])
    assert framed.position_error_m.to_numpy()[0] == pytest.approx(expected.position_error_m, abs=1e-9)


def test_a_job_past_its_deadline_stops_between_episodes(zenoh_router, box):
    """A 300-pose job (about 30 s of pushes) whose caller waits 1.5 s: "timeout", and the worker is free at once."""
    session = open_session(BusConfig(connect=[zenoh_router], connect_timeout_ms=5000))
    worker = Worker("validator-deadline", {ValidationJob: validate}, worker_id="v-1", session=session)
    thread = threading.Thread(target=worker.run)
    thread.start()
    key = job_key("validator-deadline", "v-1")

    def call(job: ValidationJob, **options):
        [reply] = list(session.get(key, payload=encode(job)[0], encoding=encode(job)[1], timeout=60, **options))
        return decode(reply.ok.payload.to_bytes(), str(reply.ok.encoding))

    try:
        deadline = time.monotonic() + 10
        while "v-1" not in live_workers(session, "validator-deadline").get("validator-deadline", []):
            assert time.monotonic() < deadline, "the validator worker did not come up"
            time.sleep(0.05)
        spatula = spatula_pose(load_hand("allegro"), box.vertices_d)
        warm = call(ValidationJob(object=ObjectRef(library_id=BOX_ID), hand="allegro", poses=spatula[None]))
        assert isinstance(warm, ValidationResult) and warm.success.to_numpy().all()  # scene built, no deadline hit
        big = ValidationJob(object=ObjectRef(library_id=BOX_ID), hand="allegro", poses=np.repeat(spatula[None], 300, 0))
        started = time.monotonic()
        answer = call(big, attachment=timeout_attachment(1.5))
        assert isinstance(answer, ErrorReply) and answer.code == "timeout", answer
        while worker.status().in_flight:  # the episode loop checks the deadline between pushes
            assert time.monotonic() - started < 3.0, "the job kept its worker busy past its deadline"
            time.sleep(0.02)
    finally:
        worker.stop()
        thread.join(15)
        session.close()


def test_a_failed_push_says_why_toppled_before_turned_before_untouched_before_missed():
    from shared.validation.push import PushOutcome

    def outcome(success=False, error=0.1, rotation=5.0, tilt=5.0, contact=1.0):
        return PushOutcome(success=success, position_error_m=error, rotation_deg=rotation, max_tilt_deg=tilt,
                           contact_fraction=contact, contact_kept=contact >= 0.8, hand_table_contact=False,
                           initial_penetration_m=0.0)

    assert outcome(success=True, error=0.01).failure() is None
    assert outcome(rotation=120.0, tilt=80.0).failure() == "toppled"
    assert outcome(rotation=60.0).failure() == "turned"
    assert outcome(contact=0.0, error=0.2).failure() == "no contact"
    assert outcome(error=0.05).failure() == "missed"

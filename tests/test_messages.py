"""Message contracts: bad input is rejected with a message that names the problem."""
from __future__ import annotations

import json

import msgpack
import numpy as np
import pytest
from pydantic import ValidationError

from shared.contracts import messages as m

BOX = m.ObjectRef(library_id="box")
POSE0 = m.ObjectPose(position=(0.5, 0.0, 0.05))


def _poses(n: int, width: int = 25) -> np.ndarray:
    return np.zeros((n, width), np.float32)


def _plan(hand: str = "allegro", arm: str = "panda", times=(0.0, 0.5, 1.0), **kw) -> m.Plan:
    fields = dict(arm=arm, hand=hand, joint_names=["a", "b"], positions=np.zeros((len(times), 2)), times_s=np.array(times))
    return m.Plan(**(fields | kw))


def test_every_message_has_id_schema_version_and_docstring():
    for name, cls in m.MESSAGE_TYPES.items():
        assert {"id", "schema_version"} <= set(cls.model_fields), name
        assert cls.__doc__ and cls.__doc__.strip(), f"{name} has no docstring"
        json.dumps(cls.model_json_schema())  # the recorder stores this schema in MCAP


def test_ids_are_unique_by_default():
    assert m.HealthQuery().id != m.HealthQuery().id


# --- objects -----------------------------------------------------------------------------------


def test_object_ref_needs_exactly_one_source():
    with pytest.raises(ValidationError, match="exactly one of library_id, mesh, point_cloud; got none"):
        m.ObjectRef()
    blob = m.MeshBlob.from_bytes(b"solid x\nendsolid x\n", "stl")
    with pytest.raises(ValidationError, match=r"got \['library_id', 'mesh'\]"):
        m.ObjectRef(library_id="box", mesh=blob)


@pytest.mark.parametrize("bad", ["../../etc/passwd", "/tmp/x.obj", "proc-box-000/../x", "a..b", "mesh-../../x",
                                 "dir\\x.obj", ".hidden", "", "x" * 129])
def test_library_id_is_an_id_never_a_path(bad):
    with pytest.raises(ValidationError, match="library_id"):
        m.ObjectRef(library_id=bad)


def test_library_ids_of_every_kind_are_accepted():
    for good in ("rnd-042", "pb-cube-small", "proc-box-017", "mesh-0123456789ab", "box", "obj.v2_1"):
        assert m.ObjectRef(library_id=good).object_id == good


def test_object_ids_are_stable_content_ids():
    blob = m.MeshBlob.from_bytes(b"v 0 0 0\n", "obj")
    assert m.ObjectRef(mesh=blob).object_id == f"mesh:{blob.sha256[:16]}"
    cloud = np.random.default_rng(1).normal(size=(10, 3))
    assert m.ObjectRef(point_cloud=cloud).object_id == m.ObjectRef(point_cloud=cloud.copy()).object_id
    assert BOX.object_id == "box"


def test_mesh_format_and_hash_are_checked(tmp_path):
    with pytest.raises(ValidationError, match="format"):
        m.MeshBlob.from_bytes(b"x", "fbx")
    with pytest.raises(ValidationError, match="does not match its data"):
        m.MeshBlob(sha256="0" * 64, format="obj", data=b"v 0 0 0\n")
    path = tmp_path / "cube.OBJ"
    path.write_bytes(b"v 0 0 0\n")
    assert m.MeshBlob.from_file(str(path)).format == "obj"
    with pytest.raises(ValueError, match="unsupported mesh format 'dae'"):
        m.MeshBlob.from_file(str(tmp_path / "x.dae"))


def test_point_cloud_shape_and_values():
    with pytest.raises(ValidationError, match=r"shape must be \[N, 3\], got \[4, 2\]"):
        m.ObjectRef(point_cloud=np.zeros((4, 2)))
    with pytest.raises(ValidationError, match="at least 1 row"):
        m.ObjectRef(point_cloud=np.zeros((0, 3)))
    with pytest.raises(ValidationError, match="NaN or infinity"):
        m.ObjectRef(point_cloud=np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(ValidationError, match="dtype must be one of"):
        m.ObjectRef(point_cloud=np.zeros((4, 3), np.int32))


def test_quaternion_is_normalised_and_zero_rejected():
    pose = m.ObjectPose(position=(0, 0, 0), quaternion_xyzw=(0, 0, 2, 0))
    assert pose.quaternion_xyzw == (0.0, 0.0, 1.0, 0.0)
    with pytest.raises(ValidationError, match="quaternion_xyzw must be a non-zero vector"):
        m.ObjectPose(position=(0, 0, 0), quaternion_xyzw=(0, 0, 0, 0))


def test_direction_frame_yaw_or_vector():
    assert m.DirectionFrame(object_pose=POSE0, direction_xy=(0, -3)).yaw_rad() == pytest.approx(-np.pi / 2)
    assert m.DirectionFrame(object_pose=POSE0, yaw_deg=180).yaw_rad() == pytest.approx(np.pi)
    with pytest.raises(ValidationError, match="exactly one of yaw_deg or direction_xy"):
        m.DirectionFrame(object_pose=POSE0, yaw_deg=0, direction_xy=(1, 0))
    with pytest.raises(ValidationError, match="direction_xy must be a non-zero vector"):
        m.DirectionFrame(object_pose=POSE0, direction_xy=(0, 0))


# --- requests ------------------------------------------------------------------------------------


def test_push_request_defaults():
    req = m.PushRequest(object=BOX, direction_deg=90)
    assert (req.distance_m, req.hand, req.arm, req.options.k, req.options.choice) == (0.20, "allegro", "panda", 200, "ranked")
    assert req.options == m.PlannerOptions()  # left out: the planner's default, defined once


def test_a_schema_1_push_request_is_refused_naming_the_new_shape():
    """A request of the old shape (knobs at the top, schema_version 1) gets a message that says where they went."""
    from shared.contracts.codec import CodecError, decode

    old = {"schema_version": 1, "object": {"library_id": "proc-box-013"}, "direction_deg": 90.0, "method": "fixed", "k": 50}
    with pytest.raises(CodecError, match=r"schema_version 1; this build speaks 2: schema 2 .* every planner knob into `options`"):
        decode(msgpack.packb(old), "application/msgpack;PushRequest")
    unversioned = {key: value for key, value in old.items() if key != "schema_version"}
    with pytest.raises(CodecError, match=r"method, k belong in `options` since PushRequest schema 2"):
        decode(msgpack.packb(unversioned), "application/msgpack;PushRequest")
    new = {"object": {"library_id": "proc-box-013"}, "direction_deg": 90.0, "options": {"method": "fixed", "k": 50}}
    assert decode(msgpack.packb(new), "application/msgpack;PushRequest").options.k == 50


def test_push_request_direction_xor_goal():
    with pytest.raises(ValidationError, match="exactly one of direction_deg or goal_xy"):
        m.PushRequest(object=BOX, direction_deg=0, goal_xy=(0.6, 0.2))
    with pytest.raises(ValidationError, match="exactly one of direction_deg or goal_xy"):
        m.PushRequest(object=BOX)


@pytest.mark.parametrize("k", [0, 1001])
def test_push_request_k_bounds(k):
    with pytest.raises(ValidationError, match=r"k\n.*Input should be (greater|less) than or equal to"):
        m.PushRequest(object=BOX, direction_deg=0, options=m.PlannerOptions(k=k))


@pytest.mark.parametrize("d", [0.0, -0.1, 1.5])
def test_push_request_distance_bounds(d):
    with pytest.raises(ValidationError, match="distance_m"):
        m.PushRequest(object=BOX, direction_deg=0, distance_m=d)


def test_physics_draws_are_bounded_and_only_for_rolled_out_plans():
    with pytest.raises(ValidationError, match=r"physics_draws\n.*less than or equal to 16"):
        m.PushRequest(object=BOX, direction_deg=0, options=m.PlannerOptions(physics_draws=17))
    with pytest.raises(ValidationError, match="choice 'random' rolls none out"):
        m.PushRequest(object=BOX, direction_deg=0, options=m.PlannerOptions(physics_draws=4, choice="random"))
    with pytest.raises(ValidationError, match="physics_draws is only used with with_arm=True"):
        m.ValidationJob(object=BOX, hand="allegro", poses=_poses(2), physics_draws=2)
    assert m.PushRequest(object=BOX, direction_deg=0, options=m.PlannerOptions(physics_draws=4, choice="unranked")).options.physics_draws == 4


def test_corrections_are_bounded_and_on_by_default():
    with pytest.raises(ValidationError, match=r"corrections\n.*less than or equal to 5"):
        m.PushRequest(object=BOX, direction_deg=0, options=m.PlannerOptions(corrections=6))
    assert m.PushRequest(object=BOX, direction_deg=0).options.corrections == 2  # on by default
    assert m.PushRequest(object=BOX, direction_deg=0, options=m.PlannerOptions(corrections=0)).options.corrections == 0  # open loop, as the paper


def test_unknown_hand_and_bad_pair():
    with pytest.raises(ValidationError, match=r"hand\n.*Input should be 'allegro' or 'leap'"):
        m.PushRequest(object=BOX, direction_deg=0, hand="shadow")
    with pytest.raises(ValidationError, match="hand 'leap' cannot be mounted on arm 'panda'; supported pairs: allegro\\+panda, leap\\+xarm7"):
        m.PushRequest(object=BOX, direction_deg=0, hand="leap")
    assert m.PushRequest(object=BOX, direction_deg=0, hand="leap", arm="xarm7").arm == "xarm7"


def test_obstacle_radius_positive():
    with pytest.raises(ValidationError, match="radius"):
        m.CircleObstacle(x=0, y=0, radius=0)


def test_wrong_pose_width():
    with pytest.raises(ValidationError, match=r"poses\n.*shape must be \[N, 25\], got \[3, 24\]"):
        m.ValidationJob(object=BOX, hand="allegro", poses=_poses(3, 24))
    with pytest.raises(ValidationError, match="at least 1 row"):
        m.ValidationJob(object=BOX, hand="allegro", poses=_poses(0))


def test_validation_job_pose_count_is_bounded():
    job = m.ValidationJob(object=BOX, hand="allegro", poses=_poses(m.MAX_BATCH_POSES))
    assert job.poses.shape == [m.MAX_BATCH_POSES, 25]
    with pytest.raises(ValidationError, match=f"{m.MAX_BATCH_POSES + 1} rows; at most {m.MAX_BATCH_POSES}"):
        m.ValidationJob(object=BOX, hand="allegro", poses=_poses(m.MAX_BATCH_POSES + 1))
    with pytest.raises(ValidationError, match="less than or equal to 4096"):
        m.GenerationJob(object=BOX, hand="allegro", batch_size=m.MAX_BATCH_POSES + 1)


def test_generation_job_batch_bounds():
    with pytest.raises(ValidationError, match="batch_size"):
        m.GenerationJob(object=BOX, hand="allegro", batch_size=0)
    with pytest.raises(ValidationError, match="batch_size"):
        m.GenerationJob(object=BOX, hand="allegro", batch_size=4097)


def test_sample_request_bounds():
    frame = m.DirectionFrame(object_pose=POSE0, yaw_deg=0)
    with pytest.raises(ValidationError, match="sampler"):
        m.SampleRequest(object=BOX, hand="allegro", frame=frame, sampler="euler")
    with pytest.raises(ValidationError, match="k"):
        m.SampleRequest(object=BOX, hand="allegro", frame=frame, k=0)


def test_validation_job_rollout_needs_arm_plan_and_frame():
    with pytest.raises(ValidationError, match="with_arm=True needs arm, plan, frame"):
        m.ValidationJob(object=BOX, hand="allegro", poses=_poses(1), with_arm=True)
    with pytest.raises(ValidationError, match="only used with with_arm=True"):
        m.ValidationJob(object=BOX, hand="allegro", poses=_poses(1), plan=_plan())
    frame = m.DirectionFrame(object_pose=POSE0, yaw_deg=0)
    with pytest.raises(ValidationError, match="one plan and its one pose, got 2"):
        m.ValidationJob(object=BOX, hand="allegro", poses=_poses(2), with_arm=True, arm="panda", plan=_plan(), frame=frame)
    job = m.ValidationJob(object=BOX, hand="allegro", poses=_poses(1), with_arm=True, arm="panda", plan=_plan(), frame=frame)
    assert job.push_distance_m == 0.20


# --- results and plans ---------------------------------------------------------------------------


def test_generation_result_rows_must_agree():
    fields = dict(job_id="j", hand="allegro", object_id="box", poses=_poses(4), palm_normals=np.zeros((4, 3)),
                  max_penetration_m=np.zeros(4), elapsed_s=1.0)
    m.GenerationResult(energies={"fc": np.zeros(4)}, **fields)
    with pytest.raises(ValidationError, match=r"energies\[dir\] has 3 rows but there are 4 poses"):
        m.GenerationResult(energies={"fc": np.zeros(4), "dir": np.zeros(3)}, **fields)


def test_validation_result_rows_must_agree():
    n = 3
    outcomes = dict(success=np.ones(n, bool), position_error_m=np.zeros(n), rotation_deg=np.zeros(n), max_tilt_deg=np.zeros(n),
                    contact_kept=np.ones(n, bool), hand_table_contact=np.zeros(n, bool), initial_penetration_m=np.zeros(n))
    m.ValidationResult(job_id="j", hand="leap", object_id="box", **outcomes)
    with pytest.raises(ValidationError, match="rotation_deg has 2 rows but there are 3 poses"):
        m.ValidationResult(job_id="j", hand="leap", object_id="box", **(outcomes | {"rotation_deg": np.zeros(2)}))
    with pytest.raises(ValidationError, match=r"dtype must be one of \['bool'\]"):
        m.ValidationResult(job_id="j", hand="leap", object_id="box", **(outcomes | {"success": np.ones(n)}))


def test_plan_times_strictly_increasing():
    with pytest.raises(ValidationError, match="strictly increasing"):
        _plan(times=(0.0, 0.5, 0.5))
    with pytest.raises(ValidationError, match="3 waypoints but 2 times"):
        _plan(times_s=np.array([0.0, 1.0]), positions=np.zeros((3, 2)))
    with pytest.raises(ValidationError, match="2 columns but there are 3 joint names"):
        _plan(joint_names=["a", "b", "c"])


def test_plan_segments_inside_and_ordered():
    ok = _plan(segments=[m.PlanSegment(label="approach", start=0, stop=2), m.PlanSegment(label="push", start=2, stop=3)])
    assert [s.label for s in ok.segments] == ["approach", "push"]
    with pytest.raises(ValidationError, match="exceeds 3 waypoints"):
        _plan(segments=[m.PlanSegment(label="push", start=1, stop=4)])
    with pytest.raises(ValidationError, match="overlaps"):
        _plan(segments=[m.PlanSegment(label="approach", start=0, stop=2), m.PlanSegment(label="push", start=1, stop=3)])
    with pytest.raises(ValidationError, match="label"):
        m.PlanSegment(label="wiggle", start=0, stop=1)


def test_plan_pair_checked():
    with pytest.raises(ValidationError, match="cannot be mounted"):
        _plan(hand="allegro", arm="xarm7")


def test_execution_state_lengths_and_status():
    with pytest.raises(ValidationError, match="velocities has 1 values for 2 joints"):
        m.ExecutionState(stamp=0, joint_names=["a", "b"], positions=np.zeros(2), velocities=np.zeros(1))
    with pytest.raises(ValidationError, match="status"):
        m.ExecutionState(stamp=0, joint_names=[], positions=np.zeros(0), velocities=np.zeros(0), status="flying")


def test_execution_command_needs_lease_and_positive_rate():
    with pytest.raises(ValidationError, match="lease_token"):
        m.ExecutionCommand(plan=_plan(), lease_token="")
    with pytest.raises(ValidationError, match="realtime_factor"):
        m.ExecutionCommand(plan=_plan(), lease_token="gd2p/alive/planner/p1", realtime_factor=0)


def test_scale_request_count_non_negative():
    assert m.ScaleRequest(service="validator", count=0).count == 0
    with pytest.raises(ValidationError, match="count"):
        m.ScaleRequest(service="validator", count=-1)


def test_ndarray_accepts_numpy_and_checks_size():
    a = m.NDArray.from_numpy(np.arange(6, dtype=np.int32).reshape(2, 3))
    assert a.shape == [2, 3] and a.to_numpy()[1, 2] == 5
    with pytest.raises(ValidationError, match="needs 24 bytes, got 20"):
        m.NDArray(dtype="int32", shape=[2, 3], data=b"\0" * 20)
    with pytest.raises(ValidationError, match="unsupported array dtype 'complex64'"):
        m.NDArray(dtype="complex64", shape=[1], data=b"\0" * 8)

"""Codec: every registered message round-trips through msgpack; malformed payloads raise CodecError."""
from __future__ import annotations

import hashlib
import itertools
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from shared.contracts import messages as m
from shared.contracts.codec import CodecError, check_payload_size, decode, encode, encoding_for, payload_limit

# --- strategies --------------------------------------------------------------------------------

finite = st.floats(min_value=-1e3, max_value=1e3, allow_nan=False, allow_infinity=False)
non_negative = st.floats(min_value=0.0, max_value=1e3, allow_nan=False, allow_infinity=False)
positive = st.floats(min_value=1e-3, max_value=1e3, allow_nan=False, allow_infinity=False)
text = st.text(min_size=1, max_size=24)
ids = st.text(min_size=1, max_size=40)
seeds = st.integers(min_value=0, max_value=2**63 - 1)
hands = st.sampled_from(m.HANDS)
pairs = st.sampled_from(sorted(m.HAND_ARM_PAIRS))
float_dtypes = st.sampled_from([np.float32, np.float64])


def float_array(shape: tuple[int, ...]) -> st.SearchStrategy[m.NDArray]:
    elements = st.floats(min_value=-1e3, max_value=1e3, allow_nan=False, allow_infinity=False, width=32)
    return float_dtypes.flatmap(lambda dt: arrays(dt, shape, elements=elements)).map(m.NDArray.from_numpy)


def bool_array(n: int) -> st.SearchStrategy[m.NDArray]:
    return arrays(np.bool_, (n,)).map(m.NDArray.from_numpy)


def int_array(n: int) -> st.SearchStrategy[m.NDArray]:
    return arrays(np.int64, (n,), elements=st.integers(0, 10_000)).map(m.NDArray.from_numpy)


def poses(n: int) -> st.SearchStrategy[m.NDArray]:
    return float_array((n, m.POSE_DIM))


rows = st.integers(min_value=1, max_value=6)

mesh_blobs = st.builds(
    m.MeshBlob.from_bytes,
    data=st.binary(min_size=1, max_size=256),
    format=st.sampled_from(m.MESH_FORMATS),
    name=st.none() | text,
)
library_ids = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,23}", fullmatch=True).filter(lambda i: ".." not in i)
object_refs = st.one_of(
    st.builds(m.ObjectRef, library_id=library_ids, scale=st.none() | positive),
    st.builds(m.ObjectRef, mesh=mesh_blobs, scale=st.none() | positive),
    st.builds(m.ObjectRef, point_cloud=rows.flatmap(lambda n: float_array((n, 3)))),
)
quaternions = st.tuples(finite, finite, finite, finite).filter(lambda q: sum(c * c for c in q) > 1e-6)
object_poses = st.builds(m.ObjectPose, position=st.tuples(finite, finite, finite), quaternion_xyzw=quaternions)
direction_frames = st.one_of(
    st.builds(m.DirectionFrame, object_pose=object_poses, yaw_deg=finite),
    st.builds(
        m.DirectionFrame,
        object_pose=object_poses,
        direction_xy=st.tuples(finite, finite).filter(lambda v: v[0] ** 2 + v[1] ** 2 > 1e-6),
    ),
)
obstacles = st.lists(st.builds(m.CircleObstacle, x=finite, y=finite, radius=positive), max_size=3)
score_terms = st.builds(m.ScoreTerms, l_goal=finite, l_coll=finite, l_dir=finite, v=finite, alpha=finite, beta=finite, gamma=finite)
execution_results = st.builds(
    m.ExecutionResult,
    final_object_pose=object_poses,
    position_error_m=non_negative,
    rotation_deg=non_negative,
    contact_kept=st.none() | st.booleans(),
)
physics_settings = st.builds(
    m.PhysicsSettings,
    solver_iterations=st.integers(1, 1000),
    time_step_s=st.floats(1e-4, 0.1),
    push_speed_mps=st.floats(1e-3, 2.0),
)


@st.composite
def plans(draw) -> m.Plan:
    hand, arm = draw(pairs)
    steps = draw(st.integers(1, 8))
    dof = draw(st.integers(1, 9))
    gaps = draw(arrays(np.float64, (steps,), elements=st.floats(1e-3, 1.0)))
    cuts = sorted(draw(st.lists(st.integers(0, steps), max_size=4, unique=True)))
    bounds = [0, *cuts, steps]
    segments = [
        m.PlanSegment(label=draw(st.sampled_from(["approach", "push", "retreat"])), start=a, stop=b)
        for a, b in itertools.pairwise(bounds)
        if b > a
    ]
    return m.Plan(
        arm=arm,
        hand=hand,
        joint_names=[f"joint_{i}" for i in range(dof)],
        positions=draw(float_array((steps, dof))),
        times_s=np.cumsum(gaps),
        segments=segments,
        id=draw(ids),
    )


@st.composite
def generation_results(draw) -> m.GenerationResult:
    n = draw(rows)
    terms = draw(st.lists(st.sampled_from(["fc", "dis", "pen", "dir", "arm"]), unique=True, max_size=5))
    return m.GenerationResult(
        job_id=draw(ids),
        hand=draw(hands),
        object_id=draw(text),
        poses=draw(poses(n)),
        energies={t: draw(float_array((n,))) for t in terms},
        palm_normals=draw(float_array((n, 3))),
        max_penetration_m=draw(float_array((n,))),
        elapsed_s=draw(non_negative),
        energy_history={"total": draw(float_array((draw(st.integers(0, 5)),)))},
    )


def outcome_fields(draw, n: int) -> dict:
    return {
        "success": draw(bool_array(n)),
        "position_error_m": draw(float_array((n,))),
        "rotation_deg": draw(float_array((n,))),
        "max_tilt_deg": draw(float_array((n,))),
        "contact_kept": draw(bool_array(n)),
        "hand_table_contact": draw(bool_array(n)),
        "initial_penetration_m": draw(float_array((n,))),
    }


@st.composite
def validation_jobs(draw) -> m.ValidationJob:
    hand, arm = draw(pairs)
    common = dict(object=draw(object_refs), hand=hand, seed=draw(seeds), settings=draw(st.none() | physics_settings),
                  push_distance_m=draw(st.floats(1e-3, 1.0)), obstacles=draw(obstacles))
    if draw(st.booleans()):
        plan = draw(plans()).model_copy(update={"hand": hand, "arm": arm})
        return m.ValidationJob(poses=draw(poses(1)), with_arm=True, arm=arm, plan=plan, frame=draw(direction_frames), **common)
    return m.ValidationJob(poses=draw(poses(draw(rows))), augment=draw(st.booleans()), **common)


@st.composite
def validation_results(draw) -> m.ValidationResult:
    n = draw(rows)
    augmented = None
    if draw(st.booleans()):
        k = draw(st.integers(0, 4))
        augmented = m.AugmentedOutcomes(poses=draw(poses(k)) if k else np.zeros((0, 25), np.float32),
                                        parent_index=draw(int_array(k)), **outcome_fields(draw, k))
    rollout = draw(st.booleans())
    return m.ValidationResult(
        job_id=draw(ids),
        hand=draw(hands),
        object_id=draw(text),
        augmented=augmented,
        goal_error_m=draw(float_array((n,))) if rollout else None,
        collision_cost=draw(float_array((n,))) if rollout else None,
        final_object_poses=draw(st.lists(object_poses, min_size=n, max_size=n)) if rollout else None,
        elapsed_s=draw(non_negative),
        **outcome_fields(draw, n),
    )


@st.composite
def sample_responses(draw) -> m.SampleResponse:
    k = draw(rows)
    return m.SampleResponse(request_id=draw(ids), hand=draw(hands), poses_d=draw(poses(k)), poses_world=draw(poses(k)),
                            latency_s=draw(non_negative), checkpoint_id=draw(text), sampler=draw(st.sampled_from(["ddpm", "ddim"])))


@st.composite
def push_requests(draw) -> m.PushRequest:
    hand, arm = draw(pairs)
    target = {"direction_deg": draw(finite)} if draw(st.booleans()) else {"goal_xy": draw(st.tuples(finite, finite))}
    obj = draw(object_refs)  # a point cloud shows where the object stands: it comes without a pose
    pose = None if obj.point_cloud is not None else draw(st.none() | object_poses)
    options = m.PlannerOptions(k=draw(st.integers(1, 1000)), choice=draw(st.sampled_from(["ranked", "unranked", "random"])),
                               max_steps=draw(st.integers(1, 100)), method=draw(st.sampled_from(["gd2p", "nearest", "fixed"])),
                               closed_loop=draw(st.booleans()), corrections=draw(st.integers(0, m.MAX_CORRECTIONS)))
    return m.PushRequest(object=obj, object_pose=pose, distance_m=draw(st.floats(1e-3, 1.0)), hand=hand, arm=arm,
                         obstacles=draw(obstacles), seed=draw(seeds), **target, options=options)


@st.composite
def push_steps(draw) -> m.PushStep:
    return m.PushStep(chosen_pose=draw(float_array((25,))), chosen_pose_world=draw(float_array((25,))), plan=draw(plans()),
                      score=draw(st.none() | score_terms), result=draw(execution_results))


@st.composite
def push_responses(draw) -> m.PushResponse:
    return m.PushResponse(
        request_id=draw(ids), success=draw(st.booleans()), chosen_pose=draw(float_array((25,))),
        chosen_pose_world=draw(float_array((25,))), plan=draw(plans()), score=draw(st.none() | score_terms),
        result=draw(execution_results), steps=draw(st.lists(push_steps(), max_size=2)),
        recording_path=draw(st.none() | text), timings_s=draw(st.dictionaries(text, non_negative, max_size=4)),
    )


@st.composite
def execution_states(draw) -> m.ExecutionState:
    n = draw(st.integers(0, 9))
    return m.ExecutionState(
        stamp=draw(non_negative), joint_names=[f"j{i}" for i in range(n)], positions=draw(float_array((n,))),
        velocities=draw(float_array((n,))), object_pose=draw(st.none() | object_poses),
        status=draw(st.sampled_from(["idle", "executing", "done", "refused", "stopped", "error"])),
        command_id=draw(st.none() | ids), message=draw(st.text(max_size=30)), plan_time_s=draw(st.none() | non_negative),
    )


@st.composite
def object_paths(draw) -> m.ObjectPath:
    n = draw(st.integers(1, 6))
    times = np.cumsum(draw(st.lists(st.floats(0.01, 1.0), min_size=n, max_size=n)))
    quaternions = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    return m.ObjectPath(times_s=times, positions=draw(float_array((n, 3))), quaternions_xyzw=quaternions)


@st.composite
def push_decisions(draw) -> m.PushDecision:
    hand, arm = draw(pairs)
    n = draw(st.integers(0, 5))
    rollouts = draw(st.lists(st.builds(m.RolloutPreview, plan=plans(), goal_error_m=st.none() | non_negative,
                                       collision_cost=st.none() | non_negative, obstacle_contact=st.booleans(),
                                       success=st.none() | st.booleans(), object_path=st.none() | object_paths()),
                             max_size=3))
    return m.PushDecision(
        request_id=draw(st.none() | ids), push_index=draw(st.integers(0, 20)), hand=hand, arm=arm,
        object=draw(object_refs), frame=draw(direction_frames), distance_m=draw(st.none() | st.floats(1e-3, 1.0)),
        obstacles=draw(obstacles), candidates_world=draw(float_array((n, m.POSE_DIM))),
        critic_scores=draw(st.none() | float_array((n,))), rollouts=rollouts,
        chosen=draw(st.none() | st.integers(0, len(rollouts) - 1)) if rollouts else None, plan=draw(plans()), id=draw(ids))


STRATEGIES: dict[type[m.Message], st.SearchStrategy] = {
    m.ErrorReply: st.builds(m.ErrorReply, code=st.sampled_from(m.ErrorReply.CODES), message=st.text(),
                            request_type=st.none() | text, service=st.none() | text, id=ids),
    m.HealthQuery: st.builds(m.HealthQuery, id=ids),
    m.WorkerStatus: st.builds(m.WorkerStatus, service=text, worker_id=text, pid=st.integers(1, 2**31), host=text,
                              in_flight=st.integers(0, 100), uptime_s=non_negative, capabilities=st.lists(text, max_size=3)),
    m.GenerationJob: st.builds(m.GenerationJob, object=object_refs, hand=hands, batch_size=st.integers(1, 4096), seed=seeds,
                               iterations=st.none() | st.integers(1, 100_000), contacts_per_pose=st.none() | st.integers(1, 64),
                               grasp_only=st.booleans(), id=ids),
    m.GenerationResult: generation_results(),
    m.Plan: plans(),
    m.ValidationJob: validation_jobs(),
    m.ValidationResult: validation_results(),
    m.SampleRequest: st.builds(m.SampleRequest, object=object_refs, hand=hands, frame=direction_frames, k=st.integers(1, 1000),
                               sampler=st.sampled_from(["ddpm", "ddim"]), steps=st.none() | st.integers(1, 1000), seed=seeds),
    m.SampleResponse: sample_responses(),
    m.PushRequest: push_requests(),
    m.PushResponse: push_responses(),
    m.ExecutionCommand: st.builds(m.ExecutionCommand, plan=plans(), lease_token=text, realtime_factor=st.floats(1e-3, 1000.0)),
    m.ExecutionState: execution_states(),
    m.EStop: st.builds(m.EStop, reason=text, issued_by=st.none() | text),
    m.ObjectTrack: st.builds(m.ObjectTrack, stamp=non_negative, pose=object_poses, source=text,
                             command_id=st.none() | ids, plan_time_s=st.none() | non_negative),
    m.PlanHeld: st.builds(m.PlanHeld, command_id=ids, plan=plans(), expires_at=finite, reason=st.none() | text),
    m.PlanConfirm: st.builds(m.PlanConfirm, command_id=ids, operator=st.none() | text),
    m.PlanConfirmReply: st.builds(m.PlanConfirmReply, command_id=ids, accepted=st.booleans(), reason=st.text()),
    m.PushDecision: push_decisions(),
    m.ScaleRequest: st.builds(m.ScaleRequest, service=text, count=st.integers(0, 1024)),
    m.ScaleReply: st.builds(m.ScaleReply, service=text, count=st.integers(0, 1024), started=st.lists(text, max_size=3),
                            stopped=st.lists(text, max_size=3)),
}


TESTS_DIR = Path(__file__).resolve().parent


def _defined_by_tests(cls: type) -> bool:
    """Message subclasses that test helpers declare for their own purposes are not product messages."""
    module_file = getattr(sys.modules.get(cls.__module__), "__file__", None)
    return module_file is not None and TESTS_DIR in Path(module_file).resolve().parents


def test_every_registered_message_has_a_round_trip_strategy():
    product_messages = {cls for cls in m.MESSAGE_TYPES.values() if not _defined_by_tests(cls)}
    missing = sorted(cls.__name__ for cls in product_messages - set(STRATEGIES))
    assert not missing, f"add a hypothesis strategy to tests/test_codec.py for: {missing}"


@pytest.mark.parametrize("cls", list(STRATEGIES), ids=lambda c: c.__name__)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_round_trip(cls, data):
    msg = data.draw(STRATEGIES[cls])
    assert isinstance(msg, cls)
    payload, encoding = encode(msg)
    assert encoding == f"application/msgpack;{cls.__name__}" == encoding_for(cls)
    back = decode(payload, encoding, expected=cls)
    assert type(back) is cls
    assert back == msg
    assert decode(payload, encoding) == msg  # the encoding alone names the model


def test_arrays_round_trip_bit_exact():
    a = np.random.default_rng(0).normal(size=(7, 25)).astype(np.float32)
    job = m.ValidationJob(object=m.ObjectRef(library_id="box"), hand="allegro", poses=a)
    back = decode(*encode(job))
    assert back.poses.to_numpy().dtype == np.float32
    np.testing.assert_array_equal(back.poses.to_numpy(), a)


def test_big_endian_arrays_are_stored_little_endian():
    a = np.arange(6, dtype=">f8").reshape(2, 3)
    arr = m.NDArray.from_numpy(a)
    assert arr.dtype == "float64"
    np.testing.assert_array_equal(arr.to_numpy(), a)


# --- malformed payloads --------------------------------------------------------------------------


def _valid_map(msg: m.Message) -> dict:
    return msg.model_dump(mode="python")


def _pack(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


ENC = encoding_for(m.SampleRequest)


def _sample_request() -> m.SampleRequest:
    frame = m.DirectionFrame(object_pose=m.ObjectPose(position=(0.5, 0.0, 0.0)), yaw_deg=90.0)
    return m.SampleRequest(object=m.ObjectRef(library_id="box"), hand="allegro", frame=frame, k=10)


def test_garbage_bytes():
    with pytest.raises(CodecError, match="not valid msgpack"):
        decode(b"\xc1\xff\x00garbage", ENC)


def test_truncated_payload():
    payload, enc = encode(_sample_request())
    with pytest.raises(CodecError, match="not valid msgpack"):
        decode(payload[:-5], enc)


def test_payload_not_a_map():
    with pytest.raises(CodecError, match="must be a msgpack map"):
        decode(_pack([1, 2, 3]), ENC)


def test_wrong_type_in_encoding():
    payload, enc = encode(m.HealthQuery())
    with pytest.raises(CodecError, match="expected a SampleRequest but the payload is a HealthQuery"):
        decode(payload, enc, expected=m.SampleRequest)


def test_error_reply_always_accepted_so_callers_see_remote_errors():
    payload, enc = encode(m.ErrorReply(code="infeasible", message="no plan"))
    reply = decode(payload, enc, expected=m.SampleRequest)
    assert isinstance(reply, m.ErrorReply) and reply.message == "no plan"


def test_unknown_model_name():
    with pytest.raises(CodecError, match="unknown message type 'NoSuchThing'"):
        decode(_pack({"id": "x"}), "application/msgpack;NoSuchThing")


def test_unsupported_encoding():
    with pytest.raises(CodecError, match="unsupported encoding 'text/plain'"):
        decode(b"hello", "text/plain")


def test_no_type_at_all():
    with pytest.raises(CodecError, match="no message type"):
        decode(_pack({}), None)


def test_schema_version_mismatch():
    body = _valid_map(_sample_request()) | {"schema_version": m.SCHEMA_VERSION + 1}
    with pytest.raises(CodecError, match=f"schema_version {m.SCHEMA_VERSION + 1}.*speaks {m.SCHEMA_VERSION}"):
        decode(_pack(body), ENC)


def test_missing_field_is_named():
    body = _valid_map(_sample_request())
    del body["frame"]
    with pytest.raises(CodecError, match=r"invalid SampleRequest: frame: Field required"):
        decode(_pack(body), ENC)


def test_unexpected_field_is_named():
    body = _valid_map(_sample_request()) | {"colour": "red"}
    with pytest.raises(CodecError, match=r"colour: Extra inputs are not permitted"):
        decode(_pack(body), ENC)


def test_ndarray_size_mismatch_is_named():
    job = m.ValidationJob(object=m.ObjectRef(library_id="box"), hand="leap", poses=np.zeros((2, 25), np.float32))
    body = _valid_map(job)
    body["poses"]["data"] = body["poses"]["data"][:-4]
    with pytest.raises(CodecError, match=r"poses: .*needs 200 bytes, got 196"):
        decode(_pack(body), encoding_for(job))


def test_wrong_pose_width_is_named():
    body = _valid_map(m.ValidationJob(object=m.ObjectRef(library_id="box"), hand="leap", poses=np.zeros((2, 25), np.float32)))
    body["poses"] = _valid_map_array(np.zeros((2, 24), np.float32))
    with pytest.raises(CodecError, match=r"poses: .*shape must be \[N, 25\], got \[2, 24\]"):
        decode(_pack(body), encoding_for(m.ValidationJob))


def _valid_map_array(a: np.ndarray) -> dict:
    return m.NDArray.from_numpy(a).model_dump()


def test_mesh_hash_mismatch_is_named():
    blob = m.MeshBlob.from_bytes(b"v 0 0 0\n", "obj")
    body = _valid_map(m.GenerationJob(object=m.ObjectRef(mesh=blob), hand="allegro", batch_size=4))
    body["object"]["mesh"]["data"] = b"v 1 1 1\n"
    with pytest.raises(CodecError, match="does not match its data"):
        decode(_pack(body), encoding_for(m.GenerationJob))
    assert blob.sha256 == hashlib.sha256(b"v 0 0 0\n").hexdigest()


def test_encode_rejects_non_messages():
    with pytest.raises(CodecError, match="only encode"):
        encode({"id": "x"})  # type: ignore[arg-type]


def test_oversized_payload_is_refused_before_unpacking(monkeypatch):
    def unpack(*args, **kwargs):
        raise AssertionError("an oversized payload was unpacked")

    limit = m.DEFAULT_MAX_PAYLOAD_BYTES
    big = b"\x00" * (limit + 1)
    monkeypatch.setattr("shared.contracts.codec.msgpack.unpackb", unpack)
    with pytest.raises(CodecError, match=f"ValidationJob payload of {limit + 1} bytes exceeds the limit of {limit} bytes"):
        decode(big, encoding_for(m.ValidationJob))
    with pytest.raises(CodecError, match="exceeds the limit"):
        decode(big, None, expected=m.SampleRequest)


def test_payload_limits_per_message_type():
    assert payload_limit(encoding_for(m.ValidationJob)) == payload_limit(encoding_for(m.PushRequest)) == 16 * 2**20
    assert payload_limit(encoding_for(m.ValidationResult)) == payload_limit(encoding_for(m.GenerationResult)) == 64 * 2**20
    assert payload_limit("application/msgpack;NoSuchModel") == payload_limit(None) == 16 * 2**20
    check_payload_size(64 * 2**20, encoding_for(m.ValidationResult))  # a full batch result still decodes
    with pytest.raises(CodecError, match="PushRequest payload of 16777217 bytes"):
        check_payload_size(16 * 2**20 + 1, encoding_for(m.PushRequest))


def test_codec_error_is_a_value_error_for_callers_that_catch_broadly():
    assert issubclass(CodecError, ValueError)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))

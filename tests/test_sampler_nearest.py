"""The Nearest-Neighbour baseline served by the sampler service (`SampleRequest.sampler == "nearest"`).

A tiny dataset store (two train-split objects, two placements each, a few random poses per
placement) is indexed with `gd2p sampler-nn build`; a sampler worker on the in-process router
serves it. A request for an object placed exactly as one training frame must return that frame's
stored poses, in D and in the world.
"""
from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from conftest import TRUTH_TRACKED as TRUTH
from pose_store import write_pose_store
from shared.contracts.messages import (
    DirectionFrame,
    ObjectPose,
    ObjectRef,
    PlannerOptions,
    SampleRequest,
    SampleResponse,
)
from shared.frames import direction_frame, matrix_to_pos_quat, poses_d_to_world
from shared.sampling.nearest_neighbor import (
    NearestNeighborBaseline,
    NearestNeighborSampler,
    default_nn_index_path,
    half_precision_agreement,
)
from shared.world.objects import list_object_ids, load_object

HAND = "allegro"
YAWS = (0.0, 1.2)
POSES_PER_FRAME = 6


def store_objects() -> list[str]:
    train = list_object_ids("train")
    return [next(i for i in train if i.startswith(f"proc-{family}-")) for family in ("box", "cylinder")]


def stored_poses(object_id: str, yaw: float) -> np.ndarray:
    """The poses written for one frame: random but distinct per (object, yaw)."""
    seed = store_objects().index(object_id) * 10 + YAWS.index(yaw)
    return np.random.default_rng(seed).normal(0.0, 0.1, (POSES_PER_FRAME, 25)).astype(np.float32)


def write_store(directory: Path) -> Path:
    rows = [(object_id, yaw, pose) for object_id in store_objects() for yaw in YAWS for pose in stored_poses(object_id, yaw)]
    table = pa.table({
        "object_id": pa.array([r[0] for r in rows], pa.string()), "hand": pa.array([HAND] * len(rows), pa.string()),
        "pose": pa.array([r[2].tolist() for r in rows], pa.list_(pa.float32())),
        "yaw_rad": pa.array([r[1] for r in rows], pa.float64()),
    })
    return write_pose_store(directory, table)


def placed(object_id: str, yaw_in_d: float, xy=(0.5, 0.1), push_deg: float = 30.0) -> DirectionFrame:
    """A DirectionFrame whose object sits in D exactly as the training frame (object_id, yaw_in_d)."""
    T_world_D = direction_frame(np.array([*xy, 0.0]), push_deg)
    position, quaternion = matrix_to_pos_quat(T_world_D @ load_object(object_id).T_D_O(None, yaw_in_d))
    return DirectionFrame(object_pose=ObjectPose(position=tuple(position), quaternion_xyzw=tuple(quaternion)),
                          yaw_deg=push_deg)


def rows_of(poses: np.ndarray, stored: np.ndarray) -> list[int]:
    """For each pose, the row of `stored` it equals exactly (AssertionError if none)."""
    matches = [np.flatnonzero((stored.astype(np.float64) == pose).all(axis=1)) for pose in poses]
    assert all(len(m) == 1 for m in matches), "a returned pose is not one of the stored poses"
    return [int(m[0]) for m in matches]


@pytest.fixture(scope="module")
def index_path(tmp_path_factory) -> Path:
    """The tiny index, built by the CLI as a user would."""
    from cli.main import main

    work = tmp_path_factory.mktemp("nn")
    out = work / "tiny_nn.npz"
    code = main(["sampler-nn", "build", "--dataset", str(write_store(work / "store")), "--hand", HAND,
                 "--out", str(out), "--half", "--no-progress"])
    assert code == 0
    return out


@pytest.fixture(scope="module")
def dispatcher(module_router, index_path, tmp_path_factory):
    """A sampler worker serving the tiny index for allegro and a missing index for leap."""
    from shared.bus import BusConfig, Dispatcher, Worker, open_session
    from shared.sampling.server import SERVICE, handlers

    missing = tmp_path_factory.mktemp("missing") / "leap_nn.npz"
    session = open_session(BusConfig(connect=[module_router], connect_timeout_ms=5000))
    stop = threading.Event()
    worker = Worker(SERVICE, handlers(nn_indexes={HAND: index_path, "leap": missing}), worker_id="sampler-nn-test",
                    concurrency=2, stop=stop, session=session, status_period_s=0.2)
    thread = threading.Thread(target=worker.run)
    thread.start()
    try:
        with Dispatcher(session, SERVICE, timeout_s=30) as bus:
            bus.wait_for_workers(1, timeout=20)
            yield bus
    finally:
        stop.set()
        thread.join(15)
        session.close()


# ----------------------------------------------------------------------------- over the bus
def test_nearest_returns_the_matched_training_frames_stored_poses_in_d_and_world(dispatcher, index_path):
    object_id, yaw = store_objects()[1], YAWS[1]
    frame = placed(object_id, yaw)
    request = SampleRequest(object=ObjectRef(library_id=object_id), hand=HAND, frame=frame, k=4, sampler="nearest", seed=3)
    reply = dispatcher.call(request, timeout=30)
    assert isinstance(reply, SampleResponse) and reply.request_id == request.id and reply.sampler == "nearest"
    poses_d = reply.poses_d.to_numpy()
    rows = rows_of(poses_d, stored_poses(object_id, yaw))
    assert len(set(rows)) == 4  # a subset of k distinct stored poses, not the other placement's or object's
    T_world_D = direction_frame(np.array([0.5, 0.1, 0.0]), 30.0)
    np.testing.assert_allclose(reply.poses_world.to_numpy(), poses_d_to_world(poses_d, T_world_D), atol=1e-9)
    assert reply.checkpoint_id.startswith(f"nn:{index_path.name}@") and reply.checkpoint_id.endswith(f":{object_id}")
    again = dispatcher.call(request.model_copy(update={"id": "same-seed"}), timeout=30)
    np.testing.assert_array_equal(again.poses_d.to_numpy(), poses_d)  # the subset is seeded


def test_k_above_the_stored_count_returns_every_stored_pose(dispatcher):
    object_id, yaw = store_objects()[0], YAWS[0]
    request = SampleRequest(object=ObjectRef(library_id=object_id), hand=HAND, frame=placed(object_id, yaw, push_deg=-90.0),
                            k=1000, sampler="nearest")
    reply = dispatcher.call(request, timeout=30)
    poses_d = reply.poses_d.to_numpy()
    assert poses_d.shape == (POSES_PER_FRAME, 25) and reply.poses_world.to_numpy().shape == (POSES_PER_FRAME, 25)
    assert sorted(rows_of(poses_d, stored_poses(object_id, yaw))) == list(range(POSES_PER_FRAME))


def test_a_hand_without_an_index_gets_a_clear_error_saying_how_to_build_one(dispatcher):
    from shared.bus import RemoteError

    object_id = store_objects()[0]
    request = SampleRequest(object=ObjectRef(library_id=object_id), hand="leap", frame=placed(object_id, 0.0), k=5,
                            sampler="nearest")
    with pytest.raises(RemoteError, match="no usable leap nearest-neighbour index") as error:
        dispatcher.call(request, timeout=30)
    assert error.value.code == "not_implemented" and "gd2p sampler-nn build" in error.value.message
    with pytest.raises(RemoteError, match="steps") as error:  # denoising steps mean nothing to a lookup
        dispatcher.call(request.model_copy(update={"id": "steps", "hand": HAND, "steps": 10}), timeout=30)
    assert error.value.code == "bad_request"
    with pytest.raises(RemoteError, match="bad_request"):  # a cloud outside the BPS ball
        dispatcher.call(request.model_copy(update={"id": "far", "hand": HAND,
                                                   "object": ObjectRef(point_cloud=np.full((5, 3), 3.0))}), timeout=30)


# ----------------------------------------------------------------------------- index files and CLI
def test_built_index_has_a_manifest_and_fp16_features_that_retrieve_like_fp32(index_path):
    manifest = json.loads(index_path.with_name(index_path.name + ".manifest.json").read_text())
    assert manifest["hand"] == HAND and manifest["features_dtype"] == "float16"
    assert manifest["dataset"]["frames"] == 4 and manifest["dataset"]["poses_total"] == 4 * POSES_PER_FRAME
    assert len(manifest["dataset"]["sha256"]) == 64 and manifest["command"].startswith("gd2p sampler-nn build")
    assert manifest["float16_check"]["top1_agreement"] == 1.0
    # The check itself catches frames that float16 cannot tell apart: values exact in float16, and a
    # twin 1e-5 away (float16 spacing there is 1.2e-4), so both twins round to the same features.
    base = (128 + np.arange(64, dtype=np.float32)) / 1024
    twins = np.stack([base, base + np.float32(1e-5), base + 0.05])
    assert half_precision_agreement(twins)["top1_agreement"] < 1.0


def test_gd2p_sample_nearest_prints_the_matched_frames_poses(index_path, capsys):
    from cli.main import main

    object_id = store_objects()[1]
    code = main(["sample", "--object", object_id, "--hand", HAND, "--n", "1000", "--sampler", "nearest",
                 "--nn-index", str(index_path), "--json"])
    assert code == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # Not 0: the index's float16 features are ~2e-5 off per value, ~2e-3 over the 4096 of them.
    assert report["matched_object"] == object_id and report["sampler"] == "nearest" and report["bps_distance"] < 1e-2
    assert report["n"] == POSES_PER_FRAME  # the default placement is the yaw-0 frame
    rows_of(np.array([p["pose"] for p in report["poses"]]), stored_poses(object_id, 0.0))


@pytest.mark.parametrize("hand", ["allegro", "leap"])
def test_shipped_index_matches_its_manifest_and_serves_its_own_training_frames(hand, monkeypatch):
    monkeypatch.delenv(f"GD2P_SAMPLER_NN_INDEX_{hand.upper()}", raising=False)
    path = default_nn_index_path(hand)
    if not path.is_file():
        pytest.skip(f"no shipped {hand} index at {path}")
    manifest = json.loads(path.with_name(path.name + ".manifest.json").read_text())
    nearest = NearestNeighborSampler.load(path)
    index: NearestNeighborBaseline = nearest.index
    assert index.hand == hand and manifest["hand"] == hand
    assert (len(index), index.pose_count) == (manifest["dataset"]["frames"], manifest["dataset"]["poses_total"])
    assert path.stat().st_size <= 32_000_000  # float32 (v2: 1,025 frames at random yaw; --half is refused for it)
    frame = index.frames[len(index) // 2]
    pose_index = None if frame.pose_index < 0 else frame.pose_index
    T_world_D = direction_frame(np.array([0.5, 0.0, 0.0]), 0.0)
    position, quaternion = matrix_to_pos_quat(T_world_D @ load_object(frame.object_id).T_D_O(pose_index, frame.yaw_rad))
    reply = nearest.sample(frame.object_id, DirectionFrame(object_pose=ObjectPose(position=tuple(position),
                                                                                  quaternion_xyzw=tuple(quaternion)),
                                                           yaw_deg=0.0), k=1000)
    assert reply.match.frame == frame and math.isclose(reply.match.distance, 0.0, abs_tol=1e-2)
    assert reply.source_id.startswith(f"nn:{hand}_nn.npz@")


# ----------------------------------------------------------------------------- end to end
@pytest.mark.slow
def test_a_push_request_with_method_nearest_executes_a_stored_training_pose(zenoh_router, monkeypatch, tmp_path):
    """Planner + validator + robot bridge + sampler (shipped allegro index) on a router of its own (the module's
    router also has the tiny-index worker): `method="nearest"`."""
    from client.push_client import push
    from services.planner import service as planner
    from services.robot_bridge import service as bridge
    from shared.bus import BusConfig, live_workers, open_session, run_worker
    from shared.contracts.messages import PushRequest
    from shared.sampling import server as sampler
    from shared.validation import jobs as validator

    monkeypatch.delenv("GD2P_SAMPLER_NN_INDEX_ALLEGRO", raising=False)
    if not default_nn_index_path("allegro").is_file():
        pytest.skip("no shipped allegro index")
    cfg = BusConfig(mode="client", connect=[zenoh_router], connect_timeout_ms=5000)
    stop = threading.Event()
    workers = [
        threading.Thread(target=bridge.run, args=(cfg, "bridge-nn", stop), kwargs=TRUTH, daemon=True),
        threading.Thread(target=run_worker, args=(validator.SERVICE, validator.handlers(), cfg, "validator-nn"),
                         kwargs={"stop": stop}, daemon=True),
        threading.Thread(target=run_worker, args=(sampler.SERVICE, sampler.handlers(), cfg, "sampler-nn"),
                         kwargs={"stop": stop}, daemon=True),
        threading.Thread(target=planner.run, args=(cfg, "planner-nn", stop, str(tmp_path)), daemon=True),
    ]
    for worker in workers:
        worker.start()
    try:
        with open_session(cfg) as session:
            deadline = time.monotonic() + 30.0
            while not all(live_workers(session).get(s) for s in ("planner", "validator", "robot_bridge", "sampler")):
                assert time.monotonic() < deadline, "workers did not register"
                time.sleep(0.2)
        response = push(PushRequest(object=ObjectRef(library_id="proc-box-013"), direction_deg=90.0, options=PlannerOptions(method="nearest")),
                        cfg, timeout_s=240.0)
    finally:
        stop.set()
        for worker in workers:
            worker.join(timeout=15.0)
    stored = NearestNeighborBaseline.load(default_nn_index_path("allegro")).poses
    assert (stored == response.chosen_pose.to_numpy()).all(axis=1).any()  # a stored pose, not a sampled one
    assert response.success and response.result.position_error_m <= 0.03


def test_retrieval_given_k_candidates_takes_whole_frames_nearest_first(index_path):
    baseline = NearestNeighborBaseline.load(index_path)
    query = baseline.frame_features[2].astype(np.float64)
    filled = baseline.nearest_frames_poses(query, 15)
    stored = baseline.poses
    # 6 + 6 poses of the two nearest frames, then the first 3 of the third; the query's own frame first.
    blocks = [filled[:6], filled[6:12], filled[12:]]
    rows = [sorted({r // POSES_PER_FRAME for r in rows_of(block, stored)}) for block in blocks]
    assert len(filled) == 15 and all(len(r) == 1 for r in rows) and rows[0] == [2]
    distances = [float(np.linalg.norm(baseline.frame_features[r[0]] - query)) for r in rows]
    assert distances == sorted(distances) and len({r[0] for r in rows}) == 3
    assert len(baseline.nearest_frames_poses(query, 1000)) == len(stored)  # fewer stored than asked: all of them

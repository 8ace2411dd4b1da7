"""Capture BPS of training frames (shared/sampling/capture_bps.py): the planner's view of an object, for training.

The capture goes through the real simulated cameras and reconstruction; the store's resumption and the
training batch's swap are checked on their own.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from shared.sampling import capture_bps
from shared.sampling.capture_bps import (
    CaptureSettings,
    CaptureStoreError,
    build_captures,
    capture_points,
    load_captures,
)
from shared.sampling.checkpoint import load_checkpoint
from shared.sampling.dataset import Frame, frame_points, load_pose_dataset
from shared.sampling.diffusion import PoseNormalizer
from shared.sampling.nearest_neighbor import NearestNeighborBaseline
from shared.sampling.train import CaptureTensors, TrainingError, train
from shared.world.bps import BasisPointSet
from test_sampler import HAND, quiet, synthetic_objects, tiny_config, write_store


def capture_frame(frame, variant, settings, bps, cache_dir):
    """(BPS, shift) of one capture, as the store encodes it."""
    points_d, shift = capture_points(frame, variant, settings, cache_dir)
    return bps.encode(points_d).astype(np.float32), shift


def test_a_capture_is_the_frames_object_seen_by_three_cameras_in_the_reconstructions_frame(tmp_path):
    bps = BasisPointSet()
    frame, other = Frame("proc-box-003", -1, 1.2), Frame("proc-cylinder-001", -1, 0.0)
    features, shift = capture_frame(frame, 0, CaptureSettings(), bps, tmp_path)
    points = frame_points(frame)
    mesh, elsewhere = bps.encode(points), bps.encode(frame_points(other))
    error = np.abs(features - mesh).mean()
    assert 0 < error < 0.5 * np.abs(elsewhere - mesh).mean()  # its own shape, not a copy of the mesh's BPS
    assert 0 < np.linalg.norm(shift) < 0.01  # the reconstruction's centre is millimetres off the true one
    # The pose offset points the right way: the captured points sit where the mesh sits moved by the shift.
    moved = bps.encode(points + np.array([*shift, 0.0]))
    away = bps.encode(points - np.array([*shift, 0.0]))
    assert np.abs(features - moved).mean() < np.abs(features - away).mean()
    again, _ = capture_frame(frame, 0, CaptureSettings(), bps, tmp_path)
    different, _ = capture_frame(frame, 1, CaptureSettings(), bps, tmp_path)
    assert np.array_equal(features, again) and not np.array_equal(features, different)


def fake_capture(frame, variant, settings, cache_dir):
    """A stand-in capture: recognisable per frame and variant, the second variant of frame 1 unreconstructable."""
    if frame.yaw_rad == 1.0 and variant == 1:
        return None
    points = np.full((3 + variant, 3), 0.01 * (frame.yaw_rad + variant), np.float32)
    return points, np.array([0.001 * variant, 0.0], np.float32)


@pytest.mark.parametrize("keep_points", [False, True])
def test_a_killed_capture_build_resumes_with_the_missing_chunks_only(tmp_path, monkeypatch, keep_points):
    monkeypatch.setattr(capture_bps, "CHUNK_FRAMES", 1)
    calls: list[tuple[float, int]] = []
    monkeypatch.setattr(capture_bps, "capture_points",
                        lambda f, v, *rest: calls.append((f.yaw_rad, v)) or fake_capture(f, v, *rest))
    frames = [Frame("proc-box-003", -1, 0.0), Frame("proc-box-003", -1, 1.0)]
    store = tmp_path / "captures"
    built = build_captures(frames, store, CaptureSettings(), "sha", workers=1, progress=False, keep_points=keep_points)
    assert built.ok.tolist() == [[True, True], [True, False]]
    seen, _ = fake_capture(frames[1], 0, None, None)
    assert built.summary()["reconstructed"] == 3 and np.allclose(built.bps[1, 0], BasisPointSet().encode(seen))
    if keep_points:  # the critic's store: the points each BPS encodes, as captured
        assert np.array_equal(built.points(1, 0), seen) and built.points(0, 1).shape == (4, 3)
    else:
        with pytest.raises(CaptureStoreError, match="keeps no points"):
            built.points(1, 0)
    (store / "chunk-00001.npz").unlink()  # the build was killed before the second chunk landed
    with pytest.raises(CaptureStoreError, match="run the build again"):
        load_captures(store)
    calls.clear()
    resumed = build_captures(frames, store, CaptureSettings(), "sha", workers=1, progress=False, keep_points=keep_points)
    assert calls == [(1.0, 0), (1.0, 1)]
    assert np.array_equal(resumed.bps, built.bps) and np.array_equal(resumed.shift_xy, built.shift_xy)
    with pytest.raises(CaptureStoreError, match="other frames or settings"):
        build_captures(frames, store, CaptureSettings(cameras=1), "sha", workers=1, progress=False, keep_points=keep_points)
    with pytest.raises(CaptureStoreError, match="other frames or settings"):  # with points vs without
        build_captures(frames, store, CaptureSettings(), "sha", workers=1, progress=False, keep_points=not keep_points)
    with pytest.raises(CaptureStoreError, match="no captures"):
        resumed.for_frames([Frame("proc-box-004", -1, 0.0)])


def test_a_batch_swaps_the_asked_share_of_rows_to_captures_and_moves_their_poses_with_them():
    normalizer = PoseNormalizer(torch.full((25,), -0.1), torch.full((25,), 0.1))  # half range 0.1
    captures = capture_bps.FrameCaptures([Frame("a", -1, 0.0), Frame("b", -1, 0.0)],
                                         bps=np.stack([np.full((2, 4), 7.0), np.full((2, 4), 9.0)]).astype(np.float32),
                                         shift_xy=np.full((2, 2, 2), 0.002, np.float32),
                                         ok=np.array([[True, True], [False, False]]))
    tensors = CaptureTensors.from_captures(captures, normalizer, torch.device("cpu"))
    rows = torch.tensor([0, 1] * 2000)
    poses, mesh_bps = torch.zeros(len(rows), 25), torch.zeros(len(rows), 4)
    generator = torch.Generator().manual_seed(0)
    unchanged = tensors.swap(rows, poses, mesh_bps, 0.0, generator)
    assert torch.equal(unchanged[0], poses) and torch.equal(unchanged[1], mesh_bps)
    swapped_poses, swapped_bps = tensors.swap(rows, poses, mesh_bps, 0.5, generator)
    swapped = swapped_bps[:, 0] == 7.0
    assert abs(float(swapped[rows == 0].float().mean()) - 0.5) < 0.05
    assert not swapped[rows == 1].any() and (swapped_bps[rows == 1] == 0).all()  # frame b's captures failed: mesh BPS
    assert torch.allclose(swapped_poses[swapped, :2], torch.tensor(0.02)) and (swapped_poses[swapped, 2:] == 0).all()
    assert (swapped_poses[~swapped] == 0).all()


def test_training_on_captures_records_them_and_needs_both_settings(tmp_path, monkeypatch):
    monkeypatch.setattr(capture_bps, "capture_points", fake_capture)
    store = write_store(tmp_path / "store", synthetic_objects()[:3])
    config = tiny_config(steps=30, capture_fraction=0.5, captures=str(tmp_path / "captures"))
    result = train(store, HAND, tmp_path / "a.pt", config, quiet(capture_workers=1))
    manifest = load_checkpoint(result.checkpoint_path).manifest
    assert manifest["config"]["capture_fraction"] == 0.5
    assert manifest["captures"]["settings"]["cameras"] == 3 and manifest["captures"]["frames"] == 4
    assert json.loads((tmp_path / "captures" / "settings.json").read_text())["dataset_sha256"] == manifest["dataset"]["sha256"]
    with pytest.raises(TrainingError, match="go together"):
        train(store, HAND, tmp_path / "b.pt", tiny_config(steps=30, capture_fraction=0.5), quiet())


def test_a_retrieval_index_with_captures_answers_a_capture_with_the_poses_moved_into_its_frame(tmp_path):
    dataset = load_pose_dataset(write_store(tmp_path / "store", synthetic_objects()[:2]), HAND)
    first = dataset.frames[0]
    seen = BasisPointSet().encode(frame_points(first)) + 0.05  # far from every mesh key
    captures = capture_bps.FrameCaptures([first], bps=np.stack([seen, np.zeros_like(seen)])[None].astype(np.float32),
                                         shift_xy=np.array([[[0.01, -0.02], [0.0, 0.0]]], np.float32),
                                         ok=np.array([[True, False]]))
    index = NearestNeighborBaseline.from_dataset(dataset, captures=captures)
    assert len(index) == len(dataset.frames) + 1  # one key per reconstructed capture
    match = index.query(seen)
    stored = dataset.poses[dataset.frame_index == 0].astype(np.float64)
    assert match.frame == first and match.distance < 1e-3
    assert np.allclose(match.poses[:, :2], stored[:, :2] + [0.01, -0.02], atol=1e-6)
    assert np.allclose(match.poses[:, 2:], stored[:, 2:])
    mesh_match = index.query(BasisPointSet().encode(frame_points(first)))
    assert np.allclose(mesh_match.poses, stored)  # the mesh key keeps the poses where they were stored

"""Simulated RGB-D capture (shared.world.sim.camera) and `gd2p capture`: metric depth, the documented
noise model, reproducibility by seed, and the files the command writes."""
from __future__ import annotations

import dataclasses
import json
import types

import numpy as np
import pytest
import trimesh

from cli.main import main
from shared.frames import make_transform
from shared.world.objects import load_object
from shared.world.perception import load_cloud, reconstruct
from shared.world.sim.camera import DEFAULT_SIZE, StereoDepthNoise, capture_object, default_cameras

SIZE = (160, 120)


@pytest.fixture(scope="module")
def cylinder():
    obj = load_object("proc-cylinder-001")
    T_world_O = make_transform(np.eye(3), np.array([0.5, 0.05, 0.0])) @ obj.T_D_O(yaw_rad=0.2)
    return obj, T_world_O


def test_ideal_depth_back_projects_onto_the_mesh_and_the_table(cylinder):
    """OpenGL depth -> metric depth (near / far) and the renderer's intrinsics are right: ideal depth
    lands on the true surface (sub-millimetre) and the table on z = 0."""
    obj, T_world_O = cylinder
    capture = capture_object(obj, T_world_O, n_cameras=3, noise=None, size=SIZE)
    truth = obj.mesh.copy()
    truth.apply_transform(T_world_O)
    for frame, mask in zip(capture.frames, capture.object_masks, strict=True):
        on_object = dataclasses.replace(frame, depth_m=np.where(mask, frame.depth_m, 0.0)).points_world()
        table = dataclasses.replace(frame, depth_m=np.where(mask, 0.0, frame.depth_m)).points_world()
        assert len(on_object) > 50
        assert np.abs(trimesh.proximity.signed_distance(truth, on_object)).max() < 1e-3
        assert np.abs(table[:, 2]).max() < 1e-3


def test_depth_noise_grows_with_the_square_of_depth():
    """sigma_z = z^2 sigma_d / (f B): measured std within 10 % of it at 0.5, 1 and 2 m (D435: 0.9, 3.6, 14 mm)."""
    noise = dataclasses.replace(StereoDepthNoise(), random_dropout=0.0, edge_dropout=0.0)
    rng = np.random.default_rng(0)
    measured = {}
    for depth in (0.5, 1.0, 2.0):
        noisy = noise.apply(np.full((200, 200), depth), rng)
        measured[depth] = float(noisy[noisy > 0].std())
        assert measured[depth] == pytest.approx(float(noise.sigma_m(depth)), rel=0.10)
    assert noise.sigma_m(1.0) == pytest.approx(0.0036, abs=2e-4)
    assert measured[2.0] / measured[1.0] == pytest.approx(4.0, rel=0.15)


def test_depth_is_quantised_and_range_limited():
    noise = StereoDepthNoise()
    depth = np.full((100, 100), 0.8)
    depth[:, :10] = 0.1  # closer than the D435's minimum range
    depth[:, 90:] = 4.0  # beyond its range
    noisy = noise.apply(depth, np.random.default_rng(0))
    valid = noisy > 0
    np.testing.assert_allclose(noisy[valid] / noise.depth_unit_m, np.round(noisy[valid] / noise.depth_unit_m), atol=1e-6)
    assert not valid[:, :10].any() and not valid[:, 90:].any()
    assert 0.98 < valid[:, 12:88].mean() < 1.0  # random dropout (0.5 %) and the edge band only


def test_dropouts_concentrate_at_depth_edges():
    noise = dataclasses.replace(StereoDepthNoise(), random_dropout=0.0)
    depth = np.full((100, 100), 1.0)
    depth[:, 50:] = 0.7  # a foreground object's edge: 30 cm jump
    invalid = noise.apply(depth, np.random.default_rng(0)) == 0.0
    edge_band = invalid[:, 48:52].mean()
    assert 0.25 < edge_band < 0.5  # 2 of the 4 columns are at the edge, each dropped with p = 0.7
    assert invalid[:, :45].mean() == 0.0 and invalid[:, 55:].mean() == 0.0


def test_capture_is_reproducible_by_seed_and_differs_across_seeds(cylinder):
    obj, T_world_O = cylinder
    first = capture_object(obj, T_world_O, n_cameras=2, seed=5, size=SIZE)
    again = capture_object(obj, T_world_O, n_cameras=2, seed=5, size=SIZE)
    other = capture_object(obj, T_world_O, n_cameras=2, seed=6, size=SIZE)
    np.testing.assert_array_equal(first.cloud, again.cloud)
    assert first.cloud.shape != other.cloud.shape or not np.array_equal(first.cloud, other.cloud)
    assert [c.name for c in first.cameras] == ["head", "tripod"]


def test_default_size_resolves_a_small_object_at_one_metre():
    """The default (the D435's 848 x 480) puts ~630 points on a 5 cm cube 1 m from the head camera after
    table removal, three times reconstruct's minimum (half the size gave 130, under it)."""
    cube = types.SimpleNamespace(mesh=trimesh.creation.box((0.05, 0.05, 0.05)))
    T_world_O = make_transform(np.eye(3), np.array([0.50, 0.0, 0.025]))  # 0.98 m from the head camera
    capture = capture_object(cube, T_world_O, n_cameras=1, seed=0)
    assert capture.frames[0].depth_m.shape == (DEFAULT_SIZE[1], DEFAULT_SIZE[0]) == (480, 848)
    assert len(reconstruct(capture.cloud).object_points) > 500


def test_default_cameras_look_at_the_object_from_plausible_places():
    cameras = default_cameras((0.55, 0.0), 3)
    assert [c.name for c in cameras] == ["head", "tripod", "opposite"]
    for camera in cameras:
        T = camera.T_world_camera()
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
        forward = T[:3, 2]
        to_object = np.array(camera.target) - np.array(camera.eye)
        assert np.dot(forward, to_object / np.linalg.norm(to_object)) == pytest.approx(1.0)
        assert forward[2] < 0  # looking down at the table
        assert 0.3 < np.linalg.norm(to_object) < 1.2  # within a D435's good range
    with pytest.raises(ValueError, match="1, 2 or 3"):
        default_cameras((0.55, 0.0), 4)


# ----------------------------------------------------------------------------- gd2p capture
def test_cli_writes_a_readable_cloud_and_a_png(tmp_path, capsys):
    out, plot = tmp_path / "box.ply", tmp_path / "box.png"
    code = main(["capture", "--object", "proc-box-001", "--cameras", "2", "--seed", "3", "--size", "160x120",
                 "--out", str(out), "--plot", str(plot), "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    cloud = load_cloud(out)
    assert len(cloud) == summary["points"] > 1000 and summary["cameras"] == 2
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert np.abs(cloud.points[:, :2] - [0.55, 0.0]).max() <= 0.4 + 1e-9  # cropped around the object


def test_cli_rejects_bad_input_clearly(tmp_path, capsys):
    out = str(tmp_path / "x.ply")
    for argv, flag in ((["--cameras", "4"], "--cameras: must be 1, 2 or 3"), (["--pose", "nan", "0", "0"], "--pose: must be a finite")):
        with pytest.raises(SystemExit) as exit_info:
            main(["capture", "--object", "proc-box-001", "--out", out, *argv])
        assert exit_info.value.code == 2 and flag in capsys.readouterr().err
    cases = (
        (["--object", "no-such-object", "--out", out], "unknown object"),
        (["--object", str(tmp_path / "missing.obj"), "--out", out], "no such file"),
        (["--object", "proc-box-001", "--out", str(tmp_path / "x.txt")], "--out must end in .ply, .pcd, .npy"),
        (["--object", "proc-box-001", "--pose", "3", "0", "0", "--out", out], "within 1.2 m of the robot"),
        (["--object", "proc-box-001", "--size", "big", "--out", out], "--size must be WIDTHxHEIGHT"),
    )
    for argv, message in cases:
        assert main(["capture", *argv]) == 2
        assert message in capsys.readouterr().err


def test_each_camera_is_levelled_to_the_table_it_sees(cylinder):
    """Cameras off by tenths of a degree and millimetres see the table tilted and raised by up to a centimetre;
    levelled against the table in their own frames it lies on z = 0 again, and the object's points come closer
    to its surface. A frame showing too little table keeps its calibrated pose."""
    from shared.world.perception.depth import DepthFrame, Intrinsics, level_to_table
    from shared.world.sim.camera import true_camera_pose
    from shared.world.sim.world import CameraError

    obj, T_world_O = cylinder
    errors = [CameraError((0.003, -0.002, 0.003), (0.3, -0.3, 0.2)), CameraError((-0.002, 0.003, -0.003), (-0.3, 0.3, -0.1))]
    cameras = default_cameras((0.5, 0.05), 2, 0.1)
    kept = capture_object(obj, T_world_O, cameras=cameras, noise=None, size=SIZE, camera_errors=errors, level=False)
    levelled = capture_object(obj, T_world_O, cameras=cameras, noise=None, size=SIZE, camera_errors=errors)
    truth = obj.mesh.copy()
    truth.apply_transform(T_world_O)
    for before, after, mask in zip(kept.frames, levelled.frames, levelled.object_masks, strict=True):
        table = dataclasses.replace(before, depth_m=np.where(mask, 0.0, before.depth_m))
        assert np.ptp(table.points_world()[:, 2]) > 0.005  # as calibrated: the table is tilted
        assert np.abs(level_to_table(table).points_world()[:, 2]).max() < 0.001
        on_object = [dataclasses.replace(frame, depth_m=np.where(mask, frame.depth_m, 0.0)).points_world()
                     for frame in (before, after)]
        off = [np.median(np.abs(trimesh.proximity.signed_distance(truth, points))) for points in on_object]
        assert off[1] < off[0]
    far = DepthFrame(np.full((24, 32), 0.3, dtype=np.float32), Intrinsics.from_hfov(32, 24, 60.0),
                     true_camera_pose(cameras[0], None))
    assert level_to_table(far) is far  # nothing near the table: nothing to level against

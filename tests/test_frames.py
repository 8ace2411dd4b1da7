"""Frames and the 25-d pose: round trips between world and D, r6 and rotations, push and pull."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from shared import frames as F


def random_rotations(n: int, seed: int = 0) -> np.ndarray:
    return Rotation.random(n, random_state=seed).as_matrix()


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rotations = random_rotations(n, seed)
    return np.concatenate([rng.uniform(-0.3, 0.3, (n, 3)), F.matrix_to_r6(rotations), rng.uniform(-0.5, 1.5, (n, 16))], axis=1)


def test_pose_layout_constants():
    assert F.POSE_DIM == 25 and F.NUM_JOINTS == 16
    pose = np.arange(25.0)
    assert pose[F.POSITION].tolist() == [0, 1, 2]
    assert pose[F.ROTATION_6D].tolist() == [3, 4, 5, 6, 7, 8]
    assert pose[F.JOINTS].tolist() == list(range(9, 25))


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_r6_round_trip(backend):
    rotations = random_rotations(200)
    data = torch.as_tensor(rotations) if backend == "torch" else rotations
    back = F.r6_to_matrix(F.matrix_to_r6(data))
    back = back.numpy() if backend == "torch" else back
    np.testing.assert_allclose(back, rotations, atol=1e-12)


def test_r6_columns_are_the_first_two_rotation_columns():
    rotation = random_rotations(1)[0]
    np.testing.assert_allclose(F.matrix_to_r6(rotation), np.concatenate([rotation[:, 0], rotation[:, 1]]))


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_gram_schmidt_turns_any_6_vector_into_a_rotation(backend):
    raw = np.random.default_rng(1).normal(size=(100, 6)) * 3.0
    data = torch.as_tensor(raw) if backend == "torch" else raw
    rotation = F.r6_to_matrix(data)
    rotation = rotation.numpy() if backend == "torch" else rotation
    np.testing.assert_allclose(rotation @ np.swapaxes(rotation, -1, -2), np.broadcast_to(np.eye(3), (100, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rotation), 1.0, atol=1e-12)
    first = raw[:, :3] / np.linalg.norm(raw[:, :3], axis=1, keepdims=True)
    np.testing.assert_allclose(rotation[:, :, 0], first, atol=1e-12)


def test_degenerate_r6_is_rejected_in_numpy_and_clamped_in_torch():
    with pytest.raises(F.FrameError, match="degenerate"):
        F.r6_to_matrix(np.array([1.0, 0, 0, 2.0, 0, 0]))
    with pytest.raises(F.FrameError, match="last dimension 6"):
        F.r6_to_matrix(np.zeros(5))
    out = F.r6_to_matrix(torch.zeros(6))
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_pose25_matrix_round_trip(backend):
    poses = random_poses(50)
    data = torch.as_tensor(poses) if backend == "torch" else poses
    transform, joints = F.pose25_to_matrix(data)
    back = F.matrix_to_pose25(transform, joints)
    back = back.numpy() if backend == "torch" else back
    np.testing.assert_allclose(back, poses, atol=1e-12)
    assert tuple(transform.shape) == (50, 4, 4)


def test_direction_frame_axes_and_origin():
    T = F.direction_frame([0.4, -0.2, 0.07], 90.0)
    np.testing.assert_allclose(T[:3, 3], [0.4, -0.2, 0.0], atol=1e-15)  # centroid projected on the table
    np.testing.assert_allclose(T[:3, 0], [0.0, 1.0, 0.0], atol=1e-15)  # +x along the push
    np.testing.assert_allclose(T[:3, 2], [0.0, 0.0, 1.0])  # +z up
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-15)
    assert F.direction_yaw_deg(T) == pytest.approx(90.0)


def test_direction_forms_agree_and_bad_directions_fail():
    by_yaw = F.direction_frame([0, 0, 0], 30.0)
    by_xy = F.direction_frame([0, 0, 0], [math.cos(math.radians(30)), math.sin(math.radians(30))])
    by_xyz = F.direction_frame([0, 0, 0], [2 * math.cos(math.radians(30)), 2 * math.sin(math.radians(30)), 5.0])
    np.testing.assert_allclose(by_xy, by_yaw, atol=1e-12)
    np.testing.assert_allclose(by_xyz, by_yaw, atol=1e-12)  # vertical part of a 3-vector ignored
    for bad in ([0.0, 0.0], [0.0, 0.0, 1.0], [1e-12, 0.0, 1.0], [float("nan"), 1.0], [1.0, 2.0, 3.0, 4.0]):
        with pytest.raises(F.FrameError):
            F.direction_frame([0, 0, 0], bad)
    with pytest.raises(F.FrameError, match="position"):
        F.direction_frame([0, 0], 0.0)


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_poses_world_d_round_trip(backend):
    T_world_D = F.direction_frame([0.5, 0.1, 0.03], -135.0)
    poses_d = random_poses(64, seed=3)
    data = torch.as_tensor(poses_d) if backend == "torch" else poses_d
    world = F.poses_d_to_world(data, T_world_D)
    back = F.poses_world_to_d(world, T_world_D)
    back = back.numpy() if backend == "torch" else back
    np.testing.assert_allclose(back, poses_d, atol=1e-12)
    world = world.numpy() if backend == "torch" else world
    np.testing.assert_array_equal(world[:, F.JOINTS], poses_d[:, F.JOINTS])
    # the world pose is the composition T_world_D · T_D_hand
    T_d, _ = F.pose25_to_matrix(poses_d)
    T_w, _ = F.pose25_to_matrix(world)
    np.testing.assert_allclose(T_w, T_world_D @ T_d, atol=1e-12)


def test_points_world_d_round_trip_and_meaning():
    T_world_D = F.direction_frame([0.5, 0.1, 0.03], 45.0)
    ahead = np.array([0.5, 0.1, 0.0]) + 0.1 * np.array([math.sqrt(0.5), math.sqrt(0.5), 0.0]) + [0, 0, 0.02]
    np.testing.assert_allclose(F.points_world_to_d(ahead, T_world_D), [0.1, 0.0, 0.02], atol=1e-12)
    points = np.random.default_rng(0).normal(size=(100, 3))
    np.testing.assert_allclose(F.points_d_to_world(F.points_world_to_d(points, T_world_D), T_world_D), points, atol=1e-12)
    as_torch = F.points_world_to_d(torch.as_tensor(points), T_world_D)
    np.testing.assert_allclose(as_torch.numpy(), F.points_world_to_d(points, T_world_D), atol=1e-12)


def test_pull_is_a_push_toward_the_robot():
    robot, obj = np.array([0.0, 0.0, 0.0]), np.array([0.55, 0.25, 0.04])
    T_world_D = F.direction_frame(obj, F.direction_toward(obj, robot))
    robot_in_d = F.points_world_to_d(robot, T_world_D)
    assert robot_in_d[0] == pytest.approx(np.linalg.norm(obj[:2]))  # the robot is straight ahead on +x
    assert robot_in_d[1] == pytest.approx(0.0, abs=1e-12)
    # a hand behind the object in D (x < 0) is on the far side from the robot in the world
    hand_d = np.concatenate([[-0.12, 0.0, 0.05], F.matrix_to_r6(np.eye(3)), np.zeros(16)])
    hand_world = F.poses_d_to_world(hand_d, T_world_D)
    assert np.linalg.norm(hand_world[:2]) > np.linalg.norm(obj[:2]) + 0.11
    np.testing.assert_allclose(F.poses_world_to_d(hand_world, T_world_D), hand_d, atol=1e-12)


def test_quaternion_helpers_round_trip_xyzw():
    rotations = random_rotations(20, seed=5)
    quats = F.matrix_to_quat_xyzw(rotations)
    assert np.all(quats[:, 3] >= 0)
    np.testing.assert_allclose(F.quat_xyzw_to_matrix(quats), rotations, atol=1e-12)
    np.testing.assert_allclose(F.matrix_to_quat_xyzw(F.yaw_rotation(math.pi / 2)), [0, 0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)
    T = F.make_transform(rotations[0], [0.1, 0.2, 0.3])
    position, quat = F.matrix_to_pos_quat(T)
    np.testing.assert_allclose(F.pos_quat_to_matrix(position, quat), T, atol=1e-12)
    with pytest.raises(F.FrameError, match="zero norm"):
        F.quat_xyzw_to_matrix([0.0, 0.0, 0.0, 0.0])


def test_transforms_invert_and_gradients_flow_through_torch():
    T = F.make_transform(random_rotations(1)[0], [0.3, -0.1, 0.2])
    np.testing.assert_allclose(F.invert_transform(T) @ T, np.eye(4), atol=1e-12)
    poses = torch.as_tensor(random_poses(4), dtype=torch.float64).requires_grad_(True)
    F.poses_d_to_world(poses, F.direction_frame([0, 0, 0], 10.0))[:, F.POSITION].sum().backward()
    assert poses.grad is not None and torch.isfinite(poses.grad).all()
    with pytest.raises(F.FrameError):
        F.transform_points(torch.eye(4), np.zeros((2, 3)))

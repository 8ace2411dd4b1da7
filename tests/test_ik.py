"""Batched arm IK for hand poses (shared/planning/ik.py): reaches what is reachable, says so when it is not."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from shared.planning.ik import ArmIK, IKError, pose_errors
from shared.robots.arms import load_arm, mount

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def ik() -> ArmIK:
    return ArmIK("panda", "allegro")


def reachable_hand_poses(ik: ArmIK, count: int, seed: int = 0) -> np.ndarray:
    """Hand poses in front of the Panda, made by forward kinematics of configurations near home."""
    rng = np.random.default_rng(seed)
    arm = ik.arm
    q = arm.home.double().numpy() + rng.uniform(-0.5, 0.5, size=(count, arm.dof))
    q = np.clip(q, arm.joint_lower.numpy() + 0.05, arm.joint_upper.numpy() - 0.05)
    poses = ik.hand_pose(q)
    in_front = (poses[:, 0, 3] > 0.2) & (poses[:, 2, 3] > 0.05)  # ahead of the base, above the table
    return poses[in_front]


def test_reaches_reachable_hand_poses_within_5mm_and_2deg(ik):
    targets = reachable_hand_poses(ik, 60)
    assert len(targets) >= 30
    result = ik.solve_hand_poses(targets)
    assert result.success.all()
    # Check independently: flange FK of the solution composed with the mount gives the target hand pose.
    arm = load_arm("panda")
    flange = arm.flange_pose(torch.as_tensor(result.q, dtype=torch.float32)).double().numpy()
    reached = flange @ mount(arm, "allegro")
    position_error, rotation_error = pose_errors(reached, targets)
    assert position_error.max() < 0.005
    assert np.degrees(rotation_error.max()) < 2.0
    assert arm.within_limits(torch.as_tensor(result.q, dtype=torch.float32)).all()


def test_reports_failure_for_an_unreachable_pose(ik):
    targets = reachable_hand_poses(ik, 10)[:2]
    targets[1, 0, 3] = 2.0  # 2 m in front of the base: beyond the Panda's ~0.85 m reach
    result = ik.solve_hand_poses(targets)
    assert result.success.tolist() == [True, False]
    assert result.position_error_m[1] > 0.5


def test_tracks_a_straight_line_continuously(ik):
    start = ik.arm.home.double().numpy()
    line = np.repeat(ik.hand_pose(start)[None], 20, axis=0)
    line[:, 1, 3] += np.linspace(0.01, 0.20, 20)  # 20 cm sideways in 1 cm steps
    result = ik.track(line, start)
    assert result.success.all()
    steps = np.abs(np.diff(np.vstack([start, result.q]), axis=0)).max(axis=1)
    assert steps.max() < 0.1  # no branch switch between 1 cm waypoints


def test_tracks_many_lines_at_once_as_each_alone_and_stops_a_line_at_its_first_unreachable_waypoint(ik):
    starts = np.stack([ik.arm.home.double().numpy(), ik.arm.home.double().numpy() + 0.2])
    lines = np.repeat(ik.hand_pose(starts)[:, None], 20, axis=1)
    lines[0, :, 1, 3] += np.linspace(0.01, 0.20, 20)  # 20 cm sideways
    lines[1, :, 0, 3] += np.linspace(0.05, 1.00, 20)  # 1 m forward: out of reach part-way
    together = ik.track_many(lines, starts)
    for i in range(2):
        alone = ik.track(lines[i], starts[i])
        assert (together.success[i] == alone.success).all()
        reached = alone.success
        assert np.allclose(together.q[i][reached], alone.q[reached], atol=1e-4)
    assert together.success[0].all()
    first_miss = int(np.argmin(together.success[1]))
    assert 0 < first_miss < 19 and not together.success[1, first_miss:].any()


def test_rejects_malformed_targets(ik):
    with pytest.raises(IKError, match="K,4,4"):
        ik.solve_hand_poses(np.eye(3))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(IKError, match="NaN"):
        ik.solve_hand_poses(bad)

"""Arm models, the arm-hand mount and combined arm+hand URDFs, checked against PyBullet."""
from __future__ import annotations

import numpy as np
import pybullet
import pytest
import pytorch_kinematics as pk
import torch
from pybullet_utils.bullet_client import BulletClient
from scipy.spatial.transform import Rotation

from shared.frames import matrix_to_pose25
from shared.robots.arms import (
    ADAPTER_THICKNESS_M,
    ArmModelError,
    combined_urdf,
    load_arm,
    mount,
    mount_joint_name,
)
from shared.robots.hands import load_hand

ARMS = ("panda", "xarm7")


@pytest.fixture(autouse=True)
def _cache_dir(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("GD2P_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "gd2p_cache"))


def random_joints(lower: torch.Tensor, upper: torch.Tensor, count: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return lower + (upper - lower) * torch.rand(count, len(lower), generator=generator)


def pybullet_link_frames(urdf_path, joint_values: dict[str, float]) -> dict[str, np.ndarray]:
    """World frames of every URDF link of a fixed-base robot at the given joint values."""
    client = BulletClient(connection_mode=pybullet.DIRECT)
    try:
        body = client.loadURDF(str(urdf_path), useFixedBase=True)
        for joint in range(client.getNumJoints(body)):
            name = client.getJointInfo(body, joint)[1].decode()
            if name in joint_values:
                client.resetJointState(body, joint, joint_values[name])
        frames = {}
        for joint in range(client.getNumJoints(body)):
            state = client.getLinkState(body, joint, computeForwardKinematics=True)
            frame = np.eye(4)
            frame[:3, :3] = Rotation.from_quat(state[5]).as_matrix()
            frame[:3, 3] = state[4]
            frames[client.getJointInfo(body, joint)[12].decode()] = frame
        return frames
    finally:
        client.disconnect()


def assert_frames_match(ours: dict[str, np.ndarray], expected: dict[str, np.ndarray]) -> None:
    assert set(expected) <= set(ours)
    for link, frame in expected.items():
        np.testing.assert_allclose(ours[link][:3, 3], frame[:3, 3], atol=1e-5, err_msg=f"{link} position")
        np.testing.assert_allclose(ours[link][:3, :3], frame[:3, :3], atol=1e-5, err_msg=f"{link} rotation")


@pytest.mark.parametrize("name", ARMS)
def test_arm_kinematics_match_pybullet(name):
    arm = load_arm(name)
    q = random_joints(arm.joint_lower, arm.joint_upper, 3, seed=0)
    links = arm.forward(q)
    for b in range(len(q)):
        expected = pybullet_link_frames(arm.urdf_path, dict(zip(arm.joint_names, q[b].tolist(), strict=True)))
        ours = {link: links[b, i].double().numpy() for i, link in enumerate(arm.link_names)}
        assert_frames_match(ours, expected)


@pytest.mark.parametrize("name", ARMS)
def test_arm_limits_home_and_flange(name):
    arm = load_arm(name)
    assert arm.dof == 7 and len(arm.joint_names) == 7
    assert torch.all(arm.joint_lower < arm.joint_upper) and torch.all(arm.velocity_limits > 0)
    assert bool(arm.within_limits(arm.home[None])[0])
    assert not bool(arm.within_limits((arm.joint_upper + 0.1)[None])[0])
    flange = arm.flange_pose(arm.home[None])[0]
    # Home is a ready pose: flange in front of and above the base, pointing down at the table.
    assert 0.25 < float(flange[0, 3]) < 0.5 and 0.3 < float(flange[2, 3]) < 0.7
    assert float(flange[2, 2]) < -0.99
    # The Panda's gripper is removed: the dexterous hand replaces it.
    assert not any("finger" in link or link == "panda_hand" for link in arm.link_names)
    jacobian = arm.serial_chain().jacobian(arm.home[None])
    assert jacobian.shape == (1, 6, 7)


@pytest.mark.parametrize(("arm_name", "hand_name"), [("panda", "allegro"), ("xarm7", "leap")])
def test_mount_puts_the_palm_along_the_flange_axis(arm_name, hand_name):
    hand = load_hand(hand_name)
    transform = mount(arm_name, hand)
    np.testing.assert_allclose(transform[:3, :3] @ transform[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(transform[:3, :3] @ hand.palm_normal_base.double().numpy(), [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(transform[:3, :3] @ hand.finger_direction_base.double().numpy(), [1, 0, 0], atol=1e-9)
    back_of_palm = transform[:3, :3] @ hand.mount_point_base.double().numpy() + transform[:3, 3]
    np.testing.assert_allclose(back_of_palm, [0, 0, ADAPTER_THICKNESS_M], atol=1e-7)
    # The whole hand is in front of the adapter: no collision shape reaches behind the flange plate.
    state = hand.forward(hand.open_pose(1))
    for prim in hand.primitives.prims:
        center = (state.links[0, prim.link_index].double().numpy() @ prim.origin)[:3, 3]
        assert (transform[:3, :3] @ center + transform[:3, 3])[2] > ADAPTER_THICKNESS_M - 1e-6


@pytest.mark.parametrize(("arm_name", "hand_name"), [("panda", "allegro"), ("xarm7", "leap")])
def test_combined_urdf_kinematics_match_pybullet_and_compose_with_the_mount(arm_name, hand_name):
    arm, hand = load_arm(arm_name), load_hand(hand_name)
    path = combined_urdf(arm, hand)
    assert combined_urdf(arm_name, hand_name) == path  # cached
    chain = pk.build_chain_from_urdf(path.read_text()).to(dtype=torch.float32)
    joint_names = chain.get_joint_parameter_names()
    assert joint_names[:7] == list(arm.joint_names) and sorted(joint_names[7:]) == sorted(hand.joint_names)

    q_arm = random_joints(arm.joint_lower, arm.joint_upper, 2, seed=1)
    q_hand = random_joints(hand.joint_lower, hand.joint_upper, 2, seed=2)
    values = [dict(zip(arm.joint_names, a.tolist(), strict=True)) | dict(zip(hand.joint_names, h.tolist(), strict=True))
              for a, h in zip(q_arm, q_hand, strict=True)]
    frames = chain.forward_kinematics_tensor(torch.tensor([[v[n] for n in joint_names] for v in values]))
    for b in range(2):
        ours = {chain.idx_to_frame[i]: frames[i, b].double().numpy() for i in range(frames.shape[0])}
        assert_frames_match(ours, pybullet_link_frames(path, values[b]))

    # Hand base = arm flange @ mount, and the hand's own FK continues from there.
    hand_base = arm.flange_pose(q_arm) @ torch.tensor(mount(arm, hand), dtype=torch.float32)
    root = chain.frame_to_idx[hand.robot.root_link]
    torch.testing.assert_close(frames[root], hand_base, atol=1e-5, rtol=0)
    pose = matrix_to_pose25(hand_base, q_hand)
    hand_links = hand.forward(pose).links
    for link in hand.link_names:
        torch.testing.assert_close(frames[chain.frame_to_idx[link]], hand_links[:, hand.link_index(link)],
                                   atol=1e-5, rtol=0)
    assert mount_joint_name(arm_name, hand_name) in path.read_text()


def test_unknown_arm_is_rejected():
    with pytest.raises(ArmModelError, match="unknown arm"):
        load_arm("ur5")
    with pytest.raises(ArmModelError, match="unknown arm"):
        mount("ur5", "allegro")

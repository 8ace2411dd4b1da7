"""The straight-line pusher baseline: one fingertip pointing along the push at the centre of mass."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from shared.frames import pose25_to_matrix
from shared.robots.hands import load_hand
from shared.world.fixed_poses import (
    FINGERTIP_LINKS,
    SPATULA_GAP_M,
    SPATULA_TABLE_CLEARANCE_M,
    FixedPoseError,
    _hand_surface_links,
    fingertip_joints,
    fingertip_pose,
    fixed_pose,
)

BOX = np.array([[x, y, z] for x in (0.0, 0.06) for y in (-0.03, 0.03) for z in (0.0, 0.08)])  # in D, rear face x = 0


def placed_surface(hand_name: str, com_d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    hand = load_hand(hand_name)
    pose = fingertip_pose(hand, BOX, com_d)
    T = pose25_to_matrix(torch.tensor(pose[None]))[0][0].numpy()
    points, links = _hand_surface_links(hand, tuple(fingertip_joints(hand)))
    return points @ T[:3, :3].T + T[:3, 3], links == hand.link_index(FINGERTIP_LINKS[hand_name])


def test_the_fingertip_points_at_the_centre_of_mass_from_behind_the_object():
    surface, tip = placed_surface("allegro", np.array([0.03, 0.005, 0.05]))
    assert surface[:, 0].max() == pytest.approx(-SPATULA_GAP_M, abs=1e-6)  # nothing of the hand in front of it
    assert surface[tip, 0].max() == pytest.approx(-SPATULA_GAP_M, abs=1e-6)  # the fingertip leads
    np.testing.assert_allclose(surface[tip].mean(axis=0)[1:], [0.005, 0.05], atol=1e-6)  # on the line through the CoM
    assert surface[:, 2].min() >= SPATULA_TABLE_CLEARANCE_M - 1e-6
    curled = fingertip_joints(load_hand("allegro"))
    assert np.all(curled[[5, 6, 7, 9, 10, 11]] > 1.0) and np.all(curled[1:4] == 0.0)  # a fist, the index straight


def test_a_low_centre_of_mass_raises_the_finger_only_as_far_as_the_table_needs():
    surface, tip = placed_surface("allegro", np.array([0.03, 0.0, 0.002]))
    assert surface[:, 2].min() == pytest.approx(SPATULA_TABLE_CLEARANCE_M, abs=1e-6)
    assert surface[tip].mean(axis=0)[2] < 0.045  # the tucked thumb below it takes 3.5 cm


def test_a_hand_without_a_fingertip_pose_and_an_unknown_fixed_pose_are_refused():
    with pytest.raises(FixedPoseError, match="no fingertip pose for hand 'leap'"):
        fingertip_pose(load_hand("leap"), BOX, np.zeros(3))
    with pytest.raises(FixedPoseError, match="no fixed pose 'poke'"):
        fixed_pose("poke", load_hand("allegro"), BOX, np.zeros(3))


def test_the_fingertip_pusher_pushes_a_box_to_its_target(tmp_path):
    """Through the whole pipeline in the planner's own world (nominal physics, the mesh told): success."""
    from evaluation import push_protocol as protocol

    protocol._init_worker(str(tmp_path))
    protocol._system.robot.tracking_mode = "truth"
    episode = protocol.Episode("fingertip-corrected", "allegro", "proc-box-001", 60.0, 0, world="exact",
                               tracking="truth")
    record = protocol.run_episode(episode)
    assert record["success"], record
    assert record["position_error_m"] < 0.03

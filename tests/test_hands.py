"""Hand models: torch kinematics vs PyBullet, contact candidates, signed distance, self-penetration, CLI."""
from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pybullet
import pytest
import torch
import trimesh
from pybullet_utils.bullet_client import BulletClient
from scipy.spatial.transform import Rotation

from shared.frames import matrix_to_r6
from shared.robots.hands import HandModelError, load_hand
from shared.robots.hands.leap_urdf import ASSET_PATH, build_leap_urdf
from shared.robots.hands.urdf import xyz_rpy_to_matrix

HANDS = ("allegro", "leap")


@pytest.fixture(autouse=True)
def _cache_dir(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("GD2P_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "gd2p_cache"))


def random_poses(hand, count: int, seed: int, spread_m: float = 0.3) -> torch.Tensor:
    """Poses with uniformly random rotations, positions in a cube and joints inside their limits."""
    generator = torch.Generator().manual_seed(seed)
    rotations = torch.tensor(Rotation.random(count, random_state=seed).as_matrix(), dtype=torch.float32)
    pose = torch.empty(count, 25)
    pose[:, :3] = (torch.rand(count, 3, generator=generator) - 0.5) * 2 * spread_m
    pose[:, 3:9] = matrix_to_r6(rotations)
    span = hand.joint_upper - hand.joint_lower
    pose[:, 9:] = hand.joint_lower + span * torch.rand(count, hand.dof, generator=generator)
    return pose


def pybullet_link_frames(hand, pose: np.ndarray) -> dict[str, np.ndarray]:
    """URDF link frames (4x4, world) PyBullet computes for one pose vector."""
    client = BulletClient(connection_mode=pybullet.DIRECT)
    try:
        body = client.loadURDF(str(hand.urdf_path))
        rotation = np.stack((pose[3:6], pose[6:9], np.cross(pose[3:6], pose[6:9])), axis=1)
        com_position, com_orientation = hand.urdf_base_to_pybullet(pose[:3], Rotation.from_matrix(rotation).as_quat())
        client.resetBasePositionAndOrientation(body, com_position, com_orientation)
        frames = {}
        for joint in range(client.getNumJoints(body)):
            info = client.getJointInfo(body, joint)
            if info[2] != pybullet.JOINT_FIXED:
                client.resetJointState(body, joint, float(pose[9 + hand.joint_names.index(info[1].decode())]))
        for joint in range(client.getNumJoints(body)):
            state = client.getLinkState(body, joint, computeForwardKinematics=True)
            frames[client.getJointInfo(body, joint)[12].decode()] = _matrix(state[4], state[5])
        base_position, base_orientation = client.getBasePositionAndOrientation(body)
        frames[hand.robot.root_link] = _matrix(*hand.pybullet_to_urdf_base(base_position, base_orientation))
        return frames
    finally:
        client.disconnect()


def _matrix(position, quaternion_xyzw) -> np.ndarray:
    frame = np.eye(4)
    frame[:3, :3] = Rotation.from_quat(quaternion_xyzw).as_matrix()
    frame[:3, 3] = position
    return frame


@pytest.mark.parametrize("name", HANDS)
def test_torch_kinematics_match_pybullet(name):
    hand = load_hand(name)
    poses = random_poses(hand, 4, seed=1)
    state = hand.forward(poses)
    for b in range(len(poses)):
        expected = pybullet_link_frames(hand, poses[b].double().numpy())
        assert set(expected) == set(hand.link_names)
        for link, frame in expected.items():
            ours = state.links[b, hand.link_index(link)].double().numpy()
            np.testing.assert_allclose(ours[:3, 3], frame[:3, 3], atol=1e-5, err_msg=f"{name} {link} position")
            np.testing.assert_allclose(ours[:3, :3], frame[:3, :3], atol=1e-5, err_msg=f"{name} {link} rotation")


@pytest.mark.parametrize("name", HANDS)
def test_joint_order_limits_and_open_pose(name):
    hand = load_hand(name)
    assert hand.dof == 16 and len(hand.joint_names) == 16 and len(set(hand.joint_names)) == 16
    assert torch.all(hand.joint_lower < hand.joint_upper)
    assert torch.all((hand.open_joint_positions >= hand.joint_lower) & (hand.open_joint_positions <= hand.joint_upper))
    # The pose's joint entries drive the joints of the same name: moving entry k moves only that joint's subtree.
    pose = hand.open_pose(1)
    moved = pose.clone()
    k = 5
    moved[0, 9 + k] += 0.3
    child = hand.robot.joint(hand.joint_names[k]).child
    delta = (hand.forward(moved).links - hand.forward(pose).links).abs().amax((-1, -2))[0]
    assert delta[hand.link_index(child)] > 1e-3
    assert delta[hand.link_index(hand.robot.root_link)] == 0


def test_allegro_contact_candidates_follow_the_paper():
    hand = load_hand("allegro")
    candidates = hand.contact_candidates
    assert len(candidates) == 688
    counts = {name: len(idx) for name, idx in candidates.indices_by_region().items()}
    assert [counts[f"tip:link_{i}.0_tip"] for i in (3, 7, 11, 15)] == [96] * 4
    assert all(counts[f"finger:link_{i}.0"] == 16 for i in (1, 2, 3, 5, 6, 7, 9, 10, 11, 14, 15))
    assert counts["palm:palm_link"] == 128
    by_link = candidates.indices_by_link()
    assert len(by_link) == 16 and len(by_link["link_15.0_tip"]) == 96
    assert torch.all(candidates.link_index[by_link["link_14.0"]] == hand.link_index("link_14.0"))
    # Tip candidates cover the distal hemisphere of the tip sphere uniformly (mean normal ~ +z, spread wide).
    tip = candidates.normals[candidates.indices_by_region()["tip:link_3.0_tip"]]
    assert torch.all(tip[:, 2] > 0)
    assert tip.mean(0)[2] == pytest.approx(0.5, abs=0.08)  # uniform on a hemisphere: E[n_z] = 1/2


def test_leap_contact_candidates_follow_the_paper():
    candidates = load_hand("leap").contact_candidates
    counts = {name: len(idx) for name, idx in candidates.indices_by_region().items()}
    assert len(candidates) == 364
    assert [counts[f"tip:{link}"] for link in ("fingertip", "fingertip_2", "fingertip_3", "thumb_fingertip")] == [24] * 4
    assert all(counts[f"finger:{part}{s}"] == 16 for part in ("mcp_joint", "dip") for s in ("", "_2", "_3"))
    assert all(counts[f"finger:pip{s}"] == 4 for s in ("", "_2", "_3"))
    assert counts["finger:thumb_pip"] == counts["finger:thumb_dip"] == 16
    assert counts["palm:palm_lower"] == 128


@pytest.mark.parametrize("name", HANDS)
def test_candidates_lie_on_the_collision_surface_with_outward_normals(name):
    hand = load_hand(name)
    pose = random_poses(hand, 3, seed=2)
    pose[:, 9:] = hand.open_joint_positions  # other links may cover candidates once fingers cross
    state = hand.forward(pose)
    points, normals = hand.contact_candidates_world(state)
    assert torch.allclose(normals.norm(dim=-1), torch.ones(()), atol=1e-5)
    on_surface = hand.signed_distance(points, state)
    assert on_surface.abs().max() < 2e-5
    # Normals point out of the hand: stepping 2 mm along them leaves it. Candidates next to a neighbouring
    # shape (a tip hemisphere's rim meets the distal box) end up beside that shape, closer than 2 mm.
    outside = hand.signed_distance(points + 0.002 * normals, state)
    assert torch.all(outside > 1e-5)
    assert ((outside - 0.002).abs() < 1e-4).float().mean() > 0.9
    # Deterministic: rebuilding the model gives identical candidates.
    rebuilt = type(hand)(hand.spec).contact_candidates
    assert torch.equal(rebuilt.points, hand.contact_candidates.points)


@pytest.mark.parametrize("name", HANDS)
def test_palm_normal_points_out_of_the_palm(name):
    hand = load_hand(name)
    state = hand.forward(random_poses(hand, 2, seed=3))
    palm = hand.palm_normal(state)
    assert torch.allclose(palm.norm(dim=-1), torch.ones(()), atol=1e-6)
    _, normals = hand.contact_candidates_world(state)
    palm_candidates = hand.contact_candidates.indices_by_region()[f"palm:{hand.spec.palm_link}"]
    mean = torch.nn.functional.normalize(normals[:, palm_candidates].mean(1), dim=-1)
    assert torch.all((mean * palm).sum(-1) > 0.99)
    # Fingers flex towards the palm side: bending every flexion joint moves the index tip along the normal.
    tip = "link_3.0_tip" if name == "allegro" else "fingertip"
    flexion = ("joint_1.0", "joint_2.0", "joint_3.0") if name == "allegro" else ("1", "2", "3")
    pose = hand.open_pose(1)
    bent = pose.clone()
    for joint in flexion:
        bent[0, 9 + hand.joint_names.index(joint)] = 0.6
    move = hand.forward(bent).links[0, hand.link_index(tip), :3, 3] - hand.forward(pose).links[0, hand.link_index(tip), :3, 3]
    assert float(move @ hand.palm_normal_base) > 0.03


@pytest.mark.parametrize("name", HANDS)
def test_signed_distance_inside_outside_and_gradients(name):
    hand = load_hand(name)
    pose = random_poses(hand, 2, seed=4)
    state = hand.forward(pose)
    centers = torch.stack([
        torch.stack([(state.links[b, p.link_index] @ torch.tensor(p.origin, dtype=torch.float32))[:3, 3]
                     for p in hand.primitives.prims]) for b in range(2)])
    assert torch.all(hand.signed_distance(centers, state) < -0.005)
    far = state.base[:, None, :3, 3] + torch.tensor([[[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]])
    far_distance = hand.signed_distance(far, state)
    assert torch.all((far_distance > 0.8) & (far_distance < 1.0))

    # Gradients w.r.t. points and the whole pose are finite and match central differences.
    points = (state.base[:, None, :3, 3] + 0.05 * torch.randn(2, 64, 3, generator=torch.Generator().manual_seed(0)))
    points.requires_grad_(True)
    pose.requires_grad_(True)
    total = hand.signed_distance(points, hand.forward(pose)).sum()
    grad_points, grad_pose = torch.autograd.grad(total, (points, pose))
    assert torch.isfinite(grad_points).all() and torch.isfinite(grad_pose).all()
    assert torch.allclose(grad_points.norm(dim=-1), torch.ones(()), atol=1e-3)  # |grad SDF| = 1 a.e.
    eps = 1e-4  # small enough that few points cross a kink of the SDF (min over primitives, box edges)
    for index in (0, 2, 4, 9, 9 + 13, 9 + 15):
        shift = torch.zeros_like(pose)
        shift[:, index] = eps
        with torch.no_grad():
            plus = hand.signed_distance(points, hand.forward(pose + shift)).sum()
            minus = hand.signed_distance(points, hand.forward(pose - shift)).sum()
        assert float(grad_pose[:, index].sum()) == pytest.approx(float(plus - minus) / (2 * eps), rel=0.05, abs=2e-3)


def test_signed_distance_rejects_bad_shapes():
    hand = load_hand("allegro")
    state = hand.forward(hand.open_pose(2))
    with pytest.raises(HandModelError, match="points must have shape"):
        hand.signed_distance(torch.zeros(3, 5, 3), state)
    with pytest.raises(HandModelError, match="pose must have shape"):
        hand.forward(torch.zeros(2, 24))
    with pytest.raises(HandModelError, match="unknown hand"):
        load_hand("shadow")


@pytest.mark.parametrize(("name", "crossed"), [
    # Index and middle fingers bent and rotated into each other.
    ("allegro", {"joint_0.0": -0.47, "joint_1.0": 1.2, "joint_4.0": 0.47, "joint_5.0": 1.2}),
    # Index abducted onto the middle finger, middle onto the ring finger.
    ("leap", {"0": 1.0, "4": -1.0}),
])
def test_self_penetration_zero_when_open_positive_when_fingers_cross(name, crossed):
    hand = load_hand(name)
    pose = hand.open_pose(2)
    for joint, value in crossed.items():
        pose[1, 9 + hand.joint_names.index(joint)] = value
    penetration = hand.self_penetration(hand.forward(pose))
    assert penetration[0] == 0
    assert penetration[1] > 0.01
    # Never between a link and its parent: bending a finger's joints fully does not count as collision.
    assert hand.keypoints.pairs.shape[0] > 0


def test_allegro_primitives_cover_its_visual_meshes():
    """The URDF's collision boxes/spheres (used as-is) enclose the visual meshes to within a few mm."""
    hand = load_hand("allegro")
    state = hand.forward(hand.open_pose(1))
    distances = []
    for link in ET.parse(hand.urdf_path).getroot().findall("link"):
        visual = link.find("visual")
        if visual is None or visual.find("geometry/mesh") is None:
            continue
        origin = visual.find("origin")
        local = xyz_rpy_to_matrix(*(([float(v) for v in origin.get(k, "0 0 0").split()] for k in ("xyz", "rpy"))
                                   if origin is not None else ([0, 0, 0], [0, 0, 0])))
        mesh = trimesh.load(visual.find("geometry/mesh").get("filename"))
        frame = state.links[0, hand.link_index(link.get("name"))].double().numpy() @ local
        samples = trimesh.sample.sample_surface(mesh, 200, seed=0)[0] @ frame[:3, :3].T + frame[:3, 3]
        distances.append(hand.signed_distance(torch.tensor(samples, dtype=torch.float32)[None], state)[0])
    distances = torch.cat(distances)
    assert len(distances) == 21 * 200
    assert distances.max() < 0.003
    assert torch.quantile(distances, 0.95) < 0.001


def test_leap_asset_matches_its_generator():
    assert ASSET_PATH.read_text() == build_leap_urdf(), "run: python -m shared.robots.hands.leap_urdf"


def test_pybullet_base_conversion_round_trips():
    hand = load_hand("leap")
    position, quaternion = np.array([0.1, -0.2, 0.3]), Rotation.random(random_state=0).as_quat()
    com_position, com_quaternion = hand.urdf_base_to_pybullet(position, quaternion)
    assert np.linalg.norm(com_position - position) == pytest.approx(np.linalg.norm(hand.pybullet_base_com_offset[:3, 3]))
    back_position, back_quaternion = hand.pybullet_to_urdf_base(com_position, com_quaternion)
    np.testing.assert_allclose(back_position, position, atol=1e-12)
    assert abs(float(np.dot(back_quaternion, quaternion))) == pytest.approx(1.0)


def _run_cli(argv: list[str]) -> int:
    import argparse

    import cli.hands

    parser = argparse.ArgumentParser(prog="gd2p")
    cli.hands.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_hands_info_json(capsys):
    assert _run_cli(["hands", "info", "allegro", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["name"] == "allegro" and info["dof"] == 16 and info["contact_candidates"] == 688
    assert len(info["joint_names"]) == 16 and len(info["joint_limits"]) == 16
    assert "palm_link" in info["links"] and info["palm_normal"] == [1.0, 0.0, 0.0]
    assert {p["kind"] for p in info["collision_primitives"]} == {"box", "sphere"}
    assert _run_cli(["hands", "info", "leap"]) == 0
    assert "contact candidates" in capsys.readouterr().out


def test_two_installs_sharing_one_cache_each_load_their_own_meshes(tmp_path, monkeypatch):
    """A resolved URDF holds absolute mesh paths: a second install (another clone's virtualenv) must get its own
    copy, not one pointing into the first install, whose files vanish when it is deleted."""
    from shared.robots.hands import urdf

    real_share = urdf.package_share_dir()
    source = urdf.example_robot_data_file("allegro_hand_description/urdf/allegro_right_hand.urdf")
    other_share = tmp_path / "other-install" / "share"
    other_share.mkdir(parents=True)
    (other_share / "example-robot-data").symlink_to(real_share / "example-robot-data")
    monkeypatch.setenv("GD2P_CACHE_DIR", str(tmp_path / "cache"))
    first = urdf.resolved_urdf(source, "allegro_right")
    monkeypatch.setattr(urdf, "package_share_dir", lambda: other_share)
    second = urdf.resolved_urdf(source, "allegro_right")
    assert first != second
    meshes = [m.get("filename") for m in ET.parse(second).getroot().iter("mesh")]
    assert meshes and all(m.startswith(str(other_share)) for m in meshes)
    assert str(other_share) not in first.read_text()

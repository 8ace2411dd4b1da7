"""Walls on the table: in the request, in both engines, seen by the cameras, refused through the object, and the
wall task of the suite (the paper's push away from a wall 1 cm from the object)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from evaluation import push_protocol as protocol
from evaluation.tasks import WALL_ANGLE_DEG, WALL_GAP_M
from shared.contracts.codec import decode, encode
from shared.contracts.messages import CircleObstacle, ObjectRef, PushRequest, WallObstacle
from shared.frames import direction_xy, make_transform
from shared.planning.goals import check_obstacles
from shared.planning.outcome import PushError
from shared.world.objects import load_object
from shared.world.obstacles import as_discs, cut_known_obstacles, on_obstacles, wall_depth_into, wall_outline
from shared.world.push_outcome import object_pose


def box_footprint(cx: float, cy: float, half: float = 0.03) -> np.ndarray:
    return np.array([[cx - half, cy - half], [cx + half, cy - half], [cx + half, cy + half], [cx - half, cy + half]])


def test_a_request_carries_walls_and_cylinders_over_the_wire():
    request = PushRequest(object=ObjectRef(library_id="pb-mug"), object_pose=object_pose(np.eye(4)), direction_deg=0.0,
                          obstacles=[CircleObstacle(x=0.6, y=0.2, radius=0.04),
                                     WallObstacle(x=0.5, y=-0.1, yaw_deg=30.0, length_m=0.4)])
    back = decode(*encode(request))
    assert isinstance(back, PushRequest)
    assert [type(o) for o in back.obstacles] == [CircleObstacle, WallObstacle]
    assert back.obstacles == request.obstacles
    with pytest.raises(ValueError, match="length_m"):  # a wall's own error, not the cylinder's
        PushRequest.model_validate({**request.model_dump(), "obstacles": [{"x": 0.5, "y": 0.0, "length_m": -1.0}]})


def test_a_wall_through_the_object_is_refused_before_any_motion_and_one_beside_it_is_not():
    footprint = box_footprint(0.5, 0.0)
    beside = WallObstacle(x=0.5, y=0.03 + WALL_GAP_M + 0.01, length_m=0.3)  # its face 1 cm from the box's side
    check_obstacles([beside], footprint)
    through = WallObstacle(x=0.5, y=0.02, length_m=0.3)
    with pytest.raises(PushError, match=r"obstacle 1 \(a wall 0.30 m long.*reaches 20 mm into") as refused:
        check_obstacles([beside, through], footprint)
    assert refused.value.code == "bad_request"
    assert wall_depth_into(through, footprint) == pytest.approx(0.02)
    assert wall_depth_into(beside, footprint) == pytest.approx(-WALL_GAP_M)


def test_discs_cover_a_wall_for_the_path_planner():
    wall = WallObstacle(x=0.4, y=0.1, yaw_deg=35.0, length_m=0.5)
    discs = np.array(as_discs([wall, CircleObstacle(x=0.0, y=0.0, radius=0.1)]))
    assert tuple(discs[-1]) == (0.0, 0.0, 0.1)
    rng = np.random.default_rng(0)
    corners = wall_outline(wall)
    weights = rng.dirichlet(np.ones(4), size=500)  # points inside the wall's footprint
    points = weights @ corners
    gaps = np.linalg.norm(points[:, None, :] - discs[None, :-1, :2], axis=2) - discs[None, :-1, 2]
    assert np.all(gaps.min(axis=1) <= 1e-9)


def test_perception_cuts_a_walls_points_and_keeps_an_objects_face_a_centimetre_away():
    wall = WallObstacle(x=0.5, y=0.1, length_m=0.3)  # faces at y = 0.09 and 0.11, 15 cm tall
    points = np.array([[0.5, 0.09, 0.05], [0.45, 0.112, 0.14], [0.5, 0.08, 0.05], [0.5, 0.1, 0.20], [0.9, 0.1, 0.05]])
    assert on_obstacles(points, [wall], 0.006).tolist() == [True, True, False, False, False]


@pytest.fixture(scope="module")
def scene_with_walls():
    from shared.world.sim.robot_scene import RobotScene

    scene = RobotScene("panda", "allegro")
    yield scene
    scene.close()


def test_the_pybullet_robot_reports_touching_a_wall_and_the_object_may_slide_along_one(scene_with_walls):
    from shared.world.objects import write_object_urdf

    scene = scene_with_walls
    scene.clear_environment()
    obj = load_object("proc-box-001")
    T = make_transform(np.eye(3), np.array([0.55, 0.0, 0.0])) @ obj.T_D_O()
    side = float(np.max(obj.mesh.vertices @ T[:3, :3].T[:, 1]))
    scene.add_object(write_object_urdf(obj), T)
    scene.add_obstacles([WallObstacle(x=0.55, y=side + 0.0099, length_m=0.4)])  # its face against the object's side
    scene.add_obstacles([CircleObstacle(x=0.55, y=-0.5, radius=0.05)])
    for _ in range(50):
        scene.sim.step()
    assert scene.object_touches_obstacle() is False  # an object resting against a wall touches no obstacle
    home = scene.arm.home.double().numpy()
    q_hand = scene.hand.open_joint_positions.double().numpy()
    assert not scene.collisions(home, q_hand)
    wrist = scene.link_pose("panda_link7")[:3, 3]
    scene.add_obstacles([WallObstacle(x=float(wrist[0]), y=float(wrist[1]), length_m=0.3, height_m=1.0)])
    assert {hit.other for hit in scene.collisions(home, q_hand)} >= {"wall 1"}
    scene.clear_environment()
    assert scene.walls == [] and scene.obstacles == [] and scene.object is None


def test_the_mujoco_world_builds_a_wall_as_a_box_its_cameras_see():
    import mujoco

    from shared.execution.robots.mujoco.config import MujocoConfig
    from shared.execution.robots.mujoco.model import build_model
    from shared.execution.robots.mujoco.robot import MujocoRobot
    from shared.world.perception.depth import Intrinsics
    from shared.world.sim.camera import CameraPose

    wall = WallObstacle(x=0.6, y=0.3, yaw_deg=0.0, length_m=0.4, height_m=0.06)
    model = build_model(MujocoConfig("panda", "allegro"), None, [wall, CircleObstacle(x=0.3, y=-0.3, radius=0.05)])
    geom = model.geom("wall 0")
    assert int(geom.type[0]) == int(mujoco.mjtGeom.mjGEOM_BOX)
    np.testing.assert_allclose(geom.size, [0.2, 0.01, 0.03])
    np.testing.assert_allclose(geom.pos, [0.6, 0.3, 0.03])
    assert model.geom("obstacle 0").size[0] == pytest.approx(0.05)
    camera, intrinsics = CameraPose("c", (0.6, -0.1, 0.4), (0.6, 0.3, 0.03)), Intrinsics.from_hfov(64, 48, 40.0)
    with MujocoRobot(MujocoConfig("panda", "allegro")) as robot:
        ((depth, _),) = robot.render_depth([camera], intrinsics)
        robot.add_obstacles([wall])
        ((walled, robot_mask),) = robot.render_depth([camera], intrinsics)
    centre = (24, 32)
    assert walled[centre] < depth[centre] - 0.01 and not robot_mask[centre]  # the wall stands in front of the table


def test_the_image_tracker_leaves_a_known_walls_points_out_of_the_object():
    from shared.world.perception.tracking import ObjectTracker
    from shared.world.sim.camera import capture_object

    obj = load_object("proc-box-001")
    T = make_transform(np.eye(3), np.array([0.45, 0.0, 0.0])) @ obj.T_D_O()
    side = float(np.max(obj.mesh.vertices @ T[:3, :3].T[:, 1]))
    wall = WallObstacle(x=0.45, y=side + WALL_GAP_M + 0.01, length_m=0.4, height_m=0.06)
    frames = capture_object(obj, T, n_cameras=3, seed=0, obstacles=[wall]).frames
    tracker = ObjectTracker.from_mesh(obj.mesh)
    centre, radius = T[:3, 3], tracker.radius_m + 0.03
    for known, expected_on_wall in (([], True), ([wall], False)):
        tracker.reset(T, known)
        points = tracker.segment(frames, [None] * len(frames), centre, radius)
        assert bool(on_obstacles(points, [wall], 0.0).any()) is expected_on_wall


def wall_episode(trial: int = 0, method: str = "fixed-corrected") -> protocol.Episode:
    return protocol.Episode(method, "allegro", "proc-box-001", 60.0, trial, cameras=3, task="wall")


@pytest.mark.parametrize("trial", [0, 1])
def test_the_wall_task_puts_a_wall_behind_the_object_a_centimetre_away_at_an_angle_to_the_push(trial):
    episode = wall_episode(trial)
    T_put = protocol.put_down(episode, protocol.execution_world(episode))
    (wall,) = protocol.task_obstacles(episode)
    footprint = (load_object(episode.object_id).mesh.vertices @ T_put[:3, :3].T + T_put[:3, 3])[:, :2]
    assert wall_depth_into(wall, footprint) == pytest.approx(-WALL_GAP_M, abs=1e-3)
    assert abs(((wall.yaw_deg - episode.direction_deg + 90.0) % 180.0) - 90.0) == pytest.approx(WALL_ANGLE_DEG)
    toward_wall = np.array([wall.x, wall.y]) - T_put[:2, 3]
    assert float(toward_wall @ direction_xy(episode.direction_deg)) < 0.0  # the push leads away from it
    paper = protocol.Episode("fixed-corrected", "allegro", "proc-box-001", 60.0, trial, cameras=3)
    assert protocol.task_obstacles(paper) == []
    assert (paper.seed, paper.world_seed) == (episode.seed, episode.world_seed)


@pytest.mark.parametrize("direction_deg", [60.0, 180.0])
def test_the_corner_task_stands_the_object_a_centimetre_from_two_walls_that_meet_behind_it(direction_deg):
    episode = protocol.Episode("fixed-corrected", "allegro", "proc-box-001", direction_deg, 1, cameras=3, task="corner")
    T_put = protocol.put_down(episode, protocol.execution_world(episode))
    walls = protocol.task_obstacles(episode)
    footprint = (load_object(episode.object_id).mesh.vertices @ T_put[:3, :3].T + T_put[:3, 3])[:, :2]
    assert [wall_depth_into(w, footprint) for w in walls] == pytest.approx([-WALL_GAP_M] * 2, abs=1e-3)
    assert abs(walls[0].yaw_deg - walls[1].yaw_deg) == pytest.approx(2 * WALL_ANGLE_DEG)  # at right angles
    shared_corners = [p for p in wall_outline(walls[0]) if np.min(np.linalg.norm(wall_outline(walls[1]) - p, axis=1)) < 1e-9]
    assert len(shared_corners) == 1  # closed: no gap between them for the object to leave by
    corner = shared_corners[0] - T_put[:2, 3]
    assert float(corner @ direction_xy(direction_deg)) < 0.0  # the push leads out of it
    assert protocol.Episode("fixed-corrected", "allegro", "proc-box-001", direction_deg, 1, cameras=3).seed == episode.seed


def test_a_palm_square_behind_the_object_stands_in_the_wall_unless_slid_clear_of_it(tmp_path):
    """The planner, the cameras and the robot all have the wall: the fixed spatula pose as it is would stand in it;
    the planner's default also tries it slid along the face it pushes, and one of those clears the wall."""
    from dataclasses import replace

    protocol._init_worker(str(tmp_path))
    system = protocol._system
    shipped = system.settings
    system.settings = replace(shipped, slide_m=())
    try:
        record = protocol.run_episode(wall_episode(0))
    finally:
        system.settings = shipped
    assert record["outcome"] == "infeasible" and "wall 0" in record["message"]
    slid = protocol.run_episode(wall_episode(0))
    assert slid["outcome"] != "infeasible" and slid["slide_m"] == list(shipped.slide_m)
    assert not slid.get("robot_touched_wall")
    request = protocol.push_request(wall_episode(0), protocol.placement(wall_episode(0)))
    assert [type(o) for o in request.obstacles] == [WallObstacle] and request.object.point_cloud is not None
    assert math.isfinite(request.obstacles[0].x)
    robot = protocol._system.robot.robot("panda", "allegro")  # the trial's world had the wall too
    assert len(robot.scene.walls) == 1


def test_the_robot_touching_the_wall_is_a_failure_of_its_own_cause():
    from evaluation.methods import FAILURE_CAUSES, failure_cause

    record = {"success": False, "outcome": "failure", "robot_touched_wall": ["link_3.0"], "predicted_l_goal": 0.01}
    assert failure_cause(record) == "wall contact" and "wall" in FAILURE_CAUSES["wall contact"]


def test_a_users_cloud_with_a_wall_in_it_is_planned_on_without_the_wall():
    """A user's cloud is the camera's scene crop: the planner cuts the request's known walls from it before it
    reconstructs the object, so a wall 1 cm away does not join the object's cluster."""
    from shared.world.object_refs import captured_object
    from shared.world.perception import cloud_for_request
    from shared.world.sim.camera import capture_object

    obj = load_object("proc-box-001")
    T = make_transform(np.eye(3), np.array([0.45, 0.0, 0.0])) @ obj.T_D_O()
    side = float(np.max(obj.mesh.vertices @ T[:3, :3].T[:, 1]))
    wall = WallObstacle(x=0.45, y=side + WALL_GAP_M + 0.01, length_m=0.4, height_m=0.06)
    u, z = np.meshgrid(np.linspace(0.3, 0.6, 60), np.linspace(0.005, 0.06, 12))
    face = np.stack([u.ravel(), np.full(u.size, side + WALL_GAP_M), z.ravel()], axis=1)  # the wall's face the cameras see
    cloud = np.concatenate([capture_object(obj, T, n_cameras=3, seed=0).cloud, face])
    request = PushRequest(object=ObjectRef(point_cloud=cloud_for_request(cloud)), direction_deg=0.0, obstacles=[wall])
    cut = cut_known_obstacles(request)
    assert cut.object.point_cloud is not None and len(cut.object.point_cloud.to_numpy()) <= len(cloud) - len(face)

    def reaches_y(ref: ObjectRef) -> float:
        seen = captured_object(ref)
        return float(np.max(seen.model.mesh.vertices @ seen.T_world_O[:3, :3].T[:, 1]) + seen.T_world_O[1, 3])

    alone = reaches_y(ObjectRef(point_cloud=cloud_for_request(cloud[: len(cloud) - len(face)])))
    # Clear of the wall as the object alone is (less the sliver of its face nearest the wall, cut with it).
    assert side - 0.005 <= reaches_y(cut.object) <= alone + 0.001
    assert reaches_y(request.object) > alone + 0.005  # uncut, the wall joins the object
    assert cut_known_obstacles(request.model_copy(update={"obstacles": []})).object is request.object

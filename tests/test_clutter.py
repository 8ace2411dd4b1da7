"""The clutter task: neighbours standing beside the pushed object, in both engines and in the cameras' view, told to
the planner as cylinders, and judged: a neighbour moved more than 1 cm fails the trial."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from evaluation import push_protocol as protocol
from evaluation.methods import failure_cause
from evaluation.tasks import CLUTTER_BEARINGS_DEG, CLUTTER_GAP_M, CLUTTER_PROPS, NEIGHBOUR_MOVED_M
from shared.contracts.messages import CircleObstacle, ObjectRef
from shared.frames import direction_xy
from shared.world.objects import load_object
from shared.world.obstacles import distance_to_hull


def clutter_episode(trial: int = 0, method: str = "fixed-corrected", object_id: str = "pb-mug",
                    direction: float = 180.0) -> protocol.Episode:
    return protocol.Episode(method, "allegro", object_id, direction, trial, cameras=3, task="clutter")


def world_points(ref: ObjectRef, T: np.ndarray) -> np.ndarray:
    assert ref.library_id is not None
    return load_object(ref.library_id).mesh.vertices @ T[:3, :3].T + T[:3, 3]


@pytest.mark.parametrize("trial", [0, 1])
def test_neighbours_stand_one_to_three_cm_from_the_object_beside_and_behind_it(trial):
    episode = clutter_episode(trial, object_id="proc-box-001", direction=60.0)
    T_put = protocol.put_down(episode, protocol.execution_world(episode))
    neighbours = protocol.task_neighbours(episode)
    bearings = CLUTTER_BEARINGS_DEG[trial % 2]
    assert len(neighbours) == len(bearings)
    footprint = ConvexHull(world_points(ObjectRef(library_id=episode.object_id), T_put)[:, :2])
    for (ref, T), bearing in zip(neighbours, bearings, strict=True):
        assert ref.library_id in CLUTTER_PROPS
        prop = world_points(ref, T)[:, :2]
        radius = float(np.max(np.linalg.norm(prop - T[:2, 3], axis=1)))
        gap = distance_to_hull(footprint, T[:2, 3]) - radius  # the can's side to the object's nearest point
        assert CLUTTER_GAP_M[0] - 1e-6 <= gap <= CLUTTER_GAP_M[1] + 1e-6
        heading = T[:2, 3] - T_put[:2, 3]
        assert float(heading @ direction_xy(60.0 + bearing)) > 0.9 * np.linalg.norm(heading)
    again = protocol.task_neighbours(clutter_episode(trial, method="gd2p-closed-critic-p24", object_id="proc-box-001",
                                                     direction=60.0))
    assert [r for r, _ in again] == [r for r, _ in neighbours]  # every method meets the same scene
    paper = protocol.Episode("fixed-corrected", "allegro", "proc-box-001", 60.0, trial, cameras=3)
    assert protocol.task_neighbours(paper) == ()


def test_the_request_tells_each_neighbour_as_a_cylinder_around_it_as_tall_as_it_stands():
    episode = clutter_episode(0)
    neighbours = protocol.task_neighbours(episode)
    circles = protocol.neighbour_circles(neighbours)
    for circle, (ref, T) in zip(circles, neighbours, strict=True):
        points = world_points(ref, T)
        assert isinstance(circle, CircleObstacle)
        assert circle.height_m == pytest.approx(points[:, 2].max())
        assert np.all(np.hypot(points[:, 0] - circle.x, points[:, 1] - circle.y) <= circle.radius + 1e-9)
    request = protocol.push_request(episode, protocol.placement(episode), neighbours)
    assert request.obstacles == circles and request.object.point_cloud is not None


def test_a_trial_among_neighbours_runs_with_them_in_the_world_and_judges_whether_they_moved(tmp_path):
    """The palm pulls the mug toward the robot past a can standing beside it: the can stays, the trial succeeds,
    and the record says how far the can moved."""
    protocol._init_worker(str(tmp_path))
    record = protocol.run_episode(clutter_episode(1))
    assert record["outcome"] == "success", record.get("message")
    assert record["neighbours_moved_m"] == [pytest.approx(0.0, abs=0.002)]
    robot = protocol._system.robot.robot("panda", "allegro")
    assert len(robot.scene.neighbours) == 1 and robot.scene.obstacles == []  # a can, not a told cylinder


def test_a_neighbour_moved_more_than_a_centimetre_fails_of_its_own_cause():
    start = ((ObjectRef(library_id=CLUTTER_PROPS[0]), np.eye(4)),)
    moved = np.eye(4)
    moved[0, 3] = 0.015
    assert protocol.neighbours_moved_m(start, [moved]) == [0.015]
    record = {"success": False, "outcome": "failure", "neighbours_moved_m": [0.015], "predicted_l_goal": 0.01}
    assert failure_cause(record) == "neighbour moved"
    assert failure_cause({**record, "neighbours_moved_m": [NEIGHBOUR_MOVED_M / 2]}) == "world gap"


def test_the_mujoco_world_holds_neighbours_as_free_bodies_that_stand_where_they_were_put():
    from shared.execution.robots.mujoco.config import MujocoConfig
    from shared.execution.robots.mujoco.robot import MujocoRobot
    from shared.execution.robots.sim.robot import TrueWorld

    episode = clutter_episode(0)
    neighbours = protocol.task_neighbours(episode)
    T_put = protocol.put_down(episode, protocol.execution_world(episode))
    world = TrueWorld(ObjectRef(library_id=episode.object_id), T_put, neighbours=neighbours)
    with MujocoRobot(MujocoConfig("panda", "allegro")) as robot:
        robot.reset_world(world)
        robot.let_object_settle(0.5)
        poses = robot.neighbour_poses()
    assert len(poses) == 2
    for (_, T), now in zip(neighbours, poses, strict=True):
        assert np.linalg.norm(now[:3, 3] - T[:3, 3]) < 0.005


def test_a_slid_copy_keeps_its_distance_to_the_face_it_pushes_and_one_slid_past_the_object_is_dropped():
    from shared.planning.stages import slid_poses

    disc = np.array([[0.05 * np.cos(a), 0.05 * np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, 73)[:-1]])
    pose = np.zeros((1, 25))
    pose[0, :3] = [-0.07, 0.0, 0.05]  # 2 cm behind the back of a 5 cm disc, along the push (+x of D)
    slid, ok = slid_poses(pose, disc, 0.03)
    assert ok[0] and slid[0, 1] == pytest.approx(0.03)
    back = -np.sqrt(0.05**2 - 0.03**2)  # the disc's back at y = 3 cm: nearer the centre line
    assert slid[0, 0] - back == pytest.approx(-0.02, abs=0.002)  # still 2 cm behind it
    assert np.array_equal(slid[0, 3:], pose[0, 3:])  # the same orientation and fingers
    _, past = slid_poses(pose, disc, 0.06)
    assert not past[0]


def test_a_spatula_pose_a_can_stands_in_is_planned_slid_beside_it_by_default_and_refused_without_the_slide():
    """The box pushed along +y with a can 1 cm behind it, 4 cm off its centre: the spatula pose behind the box's
    centre stands in the can. The planner's default also tries each pose slid 2 and 4 cm along the face it pushes,
    and one beside the can is planned and handed to the robot; with the stage off the request is infeasible, the
    can named."""
    from evaluation.local_system import validate_here
    from shared.contracts.messages import PlannerOptions, PushRequest
    from shared.planning.outcome import PushError
    from shared.planning.pipeline import PushPipeline, PushServices
    from shared.planning.stages import PipelineSettings
    from shared.world.push_outcome import object_pose
    from test_push import BOX, _box_at

    class Planned(Exception):
        pass

    def execute(*_args, **_kwargs):
        raise Planned

    def never_sampled(*_args, **_kwargs):
        raise AssertionError("the fixed pose needs no sampler")

    request = PushRequest(object=ObjectRef(library_id=BOX), object_pose=object_pose(_box_at(0.5, 0.0)),
                          direction_deg=90.0, obstacles=[CircleObstacle(x=0.54, y=-0.063, radius=0.03, height_m=0.12)],
                          options=PlannerOptions(method="fixed", choice="random", closed_loop=False, critic=False,
                                                 corrections=0))
    assert PipelineSettings().slide_m  # the default slides
    outcomes = {}
    for name, settings in (("default", PipelineSettings(prescreen=0)), ("off", PipelineSettings(prescreen=0, slide_m=()))):
        pipeline = PushPipeline(PushServices(sample=never_sampled, validate=validate_here, execute=execute), settings)
        try:
            pipeline.run(request)
        except (Planned, PushError) as exc:
            outcomes[name] = exc
        finally:
            pipeline.close()
    assert isinstance(outcomes["default"], Planned)
    refused = outcomes["off"]
    assert isinstance(refused, PushError) and refused.code == "infeasible" and "vs obstacle 0" in refused.message


@pytest.mark.parametrize("choice", ["random", "ranked"])
def test_slid_copies_are_tried_only_after_every_pose_as_sampled_in_a_random_choice_too(choice):
    """A random feasible choice (the fixed pose's, the random baselines') takes its poses in a random order, and a
    ranked one in its own: either way a slid copy is a fallback, never chosen before a pose as sampled."""
    from types import SimpleNamespace

    from shared.contracts.messages import PlannerOptions, PushRequest
    from shared.planning.candidates import Candidates
    from shared.planning.stages import priority

    n = 12
    tier = np.repeat([0, 1], n // 2)
    candidates = Candidates(np.zeros((n, 25)), np.zeros((n, 25)), np.zeros((n, 4, 4)), np.zeros((n, 16)),
                            np.linspace(-1.0, -0.5, n), tier=tier)
    request = PushRequest(object=ObjectRef(library_id="proc-box-001"), direction_deg=0.0,
                          options=PlannerOptions(choice=choice, critic=False))
    for seed in range(5):
        order = priority(SimpleNamespace(request=request, seed=seed), candidates)
        assert sorted(order.tolist()) == list(range(n)) and set(order[: n // 2].tolist()) == set(range(n // 2))
    untiered = Candidates(*(getattr(candidates, f) for f in ("poses_d", "poses_world", "T_world_hand", "q_hands",
                                                           "l_dir")))
    if choice == "random":  # without slid copies, the order is the seed's permutation, as it always was
        assert priority(SimpleNamespace(request=request, seed=3), untiered).tolist() == \
            np.random.default_rng(3).permutation(n).tolist()


def test_a_failed_plan_is_replayed_on_the_object_the_planner_saw_without_its_neighbours():
    """The replay of a failure (why a plan failed) executes in the world the planner saw: the captured cloud holds
    the two cans too, and read as the planner reads it, without the points on the told cylinders, it is the mug
    alone, where the mug stands. Read whole, the cans stand apart as a second object no reconstruction takes
    (a final run stopped on it)."""
    from shared.world.object_refs import captured_object, load_object_ref
    from shared.world.objects import ObjectLoadError
    from shared.world.push_outcome import pose_matrix

    episode = clutter_episode(0)
    neighbours = protocol.task_neighbours(episode)
    T_start = protocol.placement(episode)
    request = protocol.push_request(episode, T_start, neighbours)
    told = protocol.told_world(request)
    assert told.obstacles == request.obstacles
    T_told = pose_matrix(told.object_pose)
    seen = load_object_ref(told.object).mesh.vertices @ T_told[:3, :3].T + T_told[:3, 3]
    mug = load_object(episode.object_id).mesh.vertices @ T_start[:3, :3].T + T_start[:3, 3]
    assert np.abs(seen[:, :2].min(axis=0) - mug[:, :2].min(axis=0)).max() < 0.01
    assert np.abs(seen[:, :2].max(axis=0) - mug[:, :2].max(axis=0)).max() < 0.01
    with pytest.raises(ObjectLoadError, match="two separate objects"):
        captured_object(request.object)

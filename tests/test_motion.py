"""Arm motion for a push (shared/planning/motion.py) and the object's multi-step path (multistep.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from shared.contracts.messages import CircleObstacle
from shared.frames import direction_frame, direction_xy, make_transform, matrix_to_r6, pose25_to_matrix
from shared.planning.candidates import Candidates, Push
from shared.planning.motion import MotionPlanner, MotionSettings, PlanningError, og, time_parameterise
from shared.planning.multistep import (
    DirectionInfeasible,
    next_push_target,
    plan_object_path,
    push_along_path,
    split_into_pushes,
    turned_pushes,
)
from shared.robots.hands import load_hand
from shared.robots.robot_limits import RobotLimits, WorkspaceBox
from shared.world.fixed_poses import spatula_pose
from shared.world.objects import load_object, write_object_urdf
from shared.world.sim.robot_scene import Collision, RobotScene

torch.set_num_threads(1)

BOX_ID = "proc-box-013"  # 13.9 x 4.6 x 7.5 cm, 0.24 kg
BOX_XY = (0.55, 0.0)
PUSH_YAW_DEG = 90.0  # sideways (+y): a direction the Panda + Allegro reach comfortably


@pytest.fixture(scope="module")
def box():
    return load_object(BOX_ID)


@pytest.fixture(scope="module")
def scene(box):
    """Panda + Allegro at the origin, the box lying long side across the push at BOX_XY."""
    with RobotScene("panda", "allegro") as robot_scene:
        robot_scene.add_object(write_object_urdf(box), box_pose(box))
        yield robot_scene


@pytest.fixture(scope="module")
def planner(scene):
    return MotionPlanner(scene)


def push_frame() -> np.ndarray:
    return direction_frame(np.array([*BOX_XY, 0.0]), PUSH_YAW_DEG)


def box_pose(box) -> np.ndarray:
    """T_world_O: resting, long side across the push direction."""
    return push_frame() @ box.T_D_O(yaw_rad=np.pi / 2)


def spatula_pre_contact(box) -> tuple[np.ndarray, np.ndarray]:
    """The fixed spatula pose (palm facing the push, fingers down) behind the box, in the world."""
    T_D_O = box.T_D_O(yaw_rad=np.pi / 2)
    vertices_d = box.mesh.vertices @ T_D_O[:3, :3].T + T_D_O[:3, 3]
    T_D_hand, joints = pose25_to_matrix(spatula_pose(load_hand("allegro"), vertices_d))
    return push_frame() @ T_D_hand, joints


def hand_above_box(height_m: float) -> np.ndarray:
    """Palm facing down (Allegro palm normal = base +x -> world -z), `height_m` above the table at the box."""
    rotation = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    return make_transform(rotation, np.array([*BOX_XY, height_m]))


def interpolate_path(path: np.ndarray, max_step_rad: float) -> np.ndarray:
    states = [path[:1]]
    for a, b in zip(path[:-1], path[1:], strict=True):
        steps = max(1, int(np.ceil(np.abs(b - a).max() / max_step_rad)))
        states.append(a + np.linspace(0.0, 1.0, steps + 1)[1:, None] * (b - a))
    return np.concatenate(states)


# ----------------------------------------------------------------------------------- joint space


def test_rrtconnect_path_to_a_configuration_above_the_box_is_collision_free(scene, planner):
    q_hand = load_hand("allegro").open_joint_positions.double().numpy()
    ik = planner.ik.solve_hand_poses(hand_above_box(0.25))
    assert ik.success[0]
    home = scene.arm.home.double().numpy()
    path = planner.plan_joint_path(home, ik.q[0], q_hand)
    assert np.allclose(path[0], home) and np.allclose(path[-1], ik.q[0])
    assert len(path) == 2  # the direct motion is free: it is the path (no detour, no random search)
    # Every state along the straight edges, 5x finer than the planner's own check, is collision-free.
    for q in interpolate_path(path, 0.002):
        assert not scene.collisions(q, q_hand), f"collision at {q}"


def test_rrtconnect_goes_around_an_obstacle_that_blocks_the_straight_path():
    q_hand = load_hand("allegro").open_joint_positions.double().numpy()
    with RobotScene("panda", "allegro") as obstacle_scene:
        obstacle_scene.add_obstacles([CircleObstacle(x=0.35, y=0.10, radius=0.05)])  # a 30 cm tall cylinder left of the home pose
        planner = MotionPlanner(obstacle_scene)
        home = obstacle_scene.arm.home.double().numpy()
        ik = planner.ik.solve_hand_poses(make_transform(hand_above_box(0.0)[:3, :3], np.array([0.40, 0.30, 0.15])))
        assert ik.success[0]
        straight = interpolate_path(np.array([home, ik.q[0]]), 0.01)
        assert any(obstacle_scene.collisions(q, q_hand) for q in straight), "test premise: the direct motion collides"
        path = planner.plan_joint_path(home, ik.q[0], q_hand)
        assert len(path) >= 3
        for q in interpolate_path(path, 0.002):
            assert not obstacle_scene.collisions(q, q_hand), f"collision at {q}"


def test_a_pushs_later_paths_go_the_way_around_found_before_without_searching_again(monkeypatch):
    """Two goals a few cm apart behind the same obstacle: the second path reuses the first's way around (no OMPL
    search) and is as collision-free; a planner without the setting, or a fresh one, searches."""
    q_hand = load_hand("allegro").open_joint_positions.double().numpy()
    with RobotScene("panda", "allegro") as obstacle_scene:
        obstacle_scene.add_obstacles([CircleObstacle(x=0.35, y=0.10, radius=0.05)])
        rotation = hand_above_box(0.0)[:3, :3]
        goals = []
        for y in (0.30, 0.28):
            ik = MotionPlanner(obstacle_scene).ik.solve_hand_poses(make_transform(rotation, np.array([0.40, y, 0.15])))
            assert ik.success[0]
            goals.append(ik.q[0])
        home = obstacle_scene.arm.home.double().numpy()
        searches: list[int] = []
        solve = og.SimpleSetup.solve
        monkeypatch.setattr(og.SimpleSetup, "solve", lambda self, *a: searches.append(1) or solve(self, *a))
        planner = MotionPlanner(obstacle_scene)
        first = planner.plan_joint_path(home, goals[0], q_hand)
        second = planner.plan_joint_path(home, goals[1], q_hand)
        assert len(searches) == 1 and planner.stats.reused_paths == 1
        assert len(first) >= 3 and np.allclose(second[1:-1], first[1:-1]) and np.allclose(second[-1], goals[1])
        for q in interpolate_path(second, 0.002):
            assert not obstacle_scene.collisions(q, q_hand), f"collision at {q}"
        MotionPlanner(obstacle_scene, settings=MotionSettings(reuse_paths=False)).plan_joint_path(home, goals[1], q_hand)
        fresh = MotionPlanner(obstacle_scene).plan_joint_path(home, goals[1], q_hand)
        assert len(searches) == 3 and len(fresh) >= 3


def test_time_parameterisation_respects_velocity_limits():
    path = np.array([[0.0, 0.0], [1.0, -0.5], [1.2, 0.5]])
    limits = np.array([1.0, 2.0])
    positions, times = time_parameterise(path, limits, dt=0.02)
    speeds = np.abs(np.diff(positions, axis=0)) / np.diff(times)[:, None]
    assert (speeds <= limits * (1 + 1e-9)).all()
    assert np.allclose(positions[-1], path[-1]) and times[0] == 0.0
    assert np.all(np.diff(times) > 0)
    # Each vertex of the path is passed through (rest-to-rest edges).
    for vertex in path:
        assert np.isclose(np.abs(positions - vertex).sum(axis=1), 0).any()


# ----------------------------------------------------------------------------------------- pushes


def test_push_plan_has_approach_push_retreat_and_passes_the_bridge_limits(box, planner):
    T_world_hand, q_hand = spatula_pre_contact(box)
    direction = push_frame()[:3, 0]
    plan = planner.plan_push(T_world_hand, q_hand, direction, 0.15)
    assert [s.label for s in plan.segments] == ["approach", "push", "retreat"]
    RobotLimits.for_robot("panda", "allegro").check_plan(plan)  # raises on any violation
    positions = plan.positions.to_numpy()
    push = plan.segments[1]
    hand_path = planner.ik.hand_pose(positions[push.start - 1: push.stop, :7])
    travel = hand_path[-1, :3, 3] - hand_path[0, :3, 3]
    assert np.dot(travel, direction) == pytest.approx(0.15, abs=0.002)
    assert np.linalg.norm(travel - np.dot(travel, direction) * direction) < 0.002
    # The hand reaches the requested pre-contact pose exactly where the push starts.
    assert np.allclose(hand_path[0][:3, 3], T_world_hand[:3, 3], atol=0.002)
    assert np.allclose(positions[0, :7], planner.arm.home.numpy(), atol=1e-6)
    assert np.allclose(positions[-1, :7], planner.arm.home.numpy(), atol=1e-6)


def test_a_plan_from_the_lines_screening_tracked_is_the_plan_made_from_scratch(box, planner):
    T_world_hand, q_hand = spatula_pre_contact(box)
    direction = push_frame()[:3, 0]
    screened = planner.screen(T_world_hand[None], q_hand[None], push=0.15 * direction)
    lines = screened.lines[0]
    assert screened.feasible[0] and lines is not None and lines.approach is not None and lines.back_off is not None
    kwargs = dict(q_pre_contact=screened.q[0], return_home=False)
    reused = planner.plan_push(T_world_hand, q_hand, direction, 0.15, lines=lines, **kwargs)
    assert planner.stats.cartesian_s == 0.0  # no waypoint was solved again
    fresh = planner.plan_push(T_world_hand, q_hand, direction, 0.15, **kwargs)
    assert reused.positions.shape == fresh.positions.shape
    assert np.abs(reused.positions.to_numpy() - fresh.positions.to_numpy()).max() < 1e-3
    assert [(s.label, s.start, s.stop) for s in reused.segments] == [(s.label, s.start, s.stop) for s in fresh.segments]


def test_screening_keeps_reachable_free_poses_and_says_why_the_others_fail(box, planner):
    T_world_hand, q_hand = spatula_pre_contact(box)
    poses = np.repeat(T_world_hand[None], 3, axis=0)
    poses[1, 2, 3] = -0.05  # into the table
    poses[2, 0, 3] = 2.0  # out of reach
    result = planner.screen(poses, np.repeat(q_hand[None], 3, axis=0))
    assert result.feasible.tolist() == [True, False, False]
    assert result.reasons[0] == ""
    assert result.reasons[1].startswith("pre-contact pose in collision") and "table" in result.reasons[1]
    assert result.reasons[2] == "no IK solution"


def test_screening_falls_back_to_the_next_ik_solution_when_the_best_one_collides(box, planner, monkeypatch):
    T_world_hand, q_hand = spatula_pre_contact(box)
    options = planner.ik.distinct_solutions(T_world_hand, limit=planner.settings.max_ik_candidates)[0]
    assert len(options) >= 2
    real_collisions = planner.scene.collisions
    elbow_hit = Collision("panda_link4", "obstacle 0", -0.02)

    def elbow_of_the_best_in_an_obstacle(q, *args, **kwargs):  # as if an obstacle stood where its elbow is
        return [elbow_hit] if np.allclose(q, options[0]) else real_collisions(q, *args, **kwargs)

    monkeypatch.setattr(planner.scene, "collisions", elbow_of_the_best_in_an_obstacle)
    result = planner.screen(T_world_hand[None], q_hand[None])
    assert result.feasible.tolist() == [True]
    assert np.allclose(result.q[0], options[1])
    monkeypatch.setattr(planner.scene, "collisions", lambda *args, **kwargs: [elbow_hit])
    result = planner.screen(T_world_hand[None], q_hand[None])
    assert result.reasons == [f"pre-contact pose in collision: {elbow_hit}"]


def test_screening_does_not_retry_ik_when_the_hand_itself_collides(box, planner, monkeypatch):
    T_world_hand, q_hand = spatula_pre_contact(box)
    calls = []

    def palm_in_the_table(q, *args, **kwargs):
        calls.append(q)
        return [Collision("link_0.0", "table", -0.05)]  # deeper than screening ever raises a pose

    monkeypatch.setattr(planner.scene, "collisions", palm_in_the_table)
    result = planner.screen(T_world_hand[None], q_hand[None])
    # one arm solution looked at (how deep the palm is included): another moves no hand link
    assert result.feasible.tolist() == [False] and len({tuple(q) for q in calls}) == 1


def table_clearance(scene, q, q_hand) -> float:
    """The hand's closest distance to the table at (q, q_hand), m (negative: in it)."""
    near = [h for h in scene.collisions(q, q_hand, clearance_m=0.05) if h.other == "table"]
    return min(h.distance_m for h in near)


def test_screening_raises_a_pose_a_few_mm_in_the_table_out_of_it_and_not_one_deep_in_it(box, planner):
    T_world_hand, q_hand = spatula_pre_contact(box)
    screened = planner.screen(T_world_hand[None], q_hand[None])
    clearance = table_clearance(planner.scene, screened.q[0], q_hand)
    s = planner.settings
    low, deep = T_world_hand.copy(), T_world_hand.copy()
    low[2, 3] -= clearance + 0.008  # the hand 8 mm in the table, as learned poses often are
    deep[2, 3] -= clearance + s.table_lift_max_m + 0.01
    result = planner.screen(np.stack([low, deep]), np.repeat(q_hand[None], 2, axis=0))
    assert result.feasible.tolist() == [True, False]
    assert result.lift_m[0] == pytest.approx(0.008 - s.contact_tolerance_m + 0.001, abs=1e-3)
    assert result.lift_m[1] == 0.0 and "table" in result.reasons[1]
    raised = table_clearance(planner.scene, result.q[0], q_hand)
    assert -s.contact_tolerance_m < raised < 0.0  # out of the table but for the tolerated graze
    flange_z = planner.arm.flange_pose(torch.as_tensor(np.stack([screened.q[0], result.q[0]]), dtype=torch.float32))[:, 2, 3]
    assert float(flange_z[1] - flange_z[0]) == pytest.approx(result.lift_m[0] - clearance - 0.008, abs=1e-3)


def test_screening_with_the_push_rejects_a_pose_whose_push_runs_out_of_reach(box, planner):
    T_world_hand, q_hand = spatula_pre_contact(box)
    direction = push_frame()[:3, 0]
    poses, hands = T_world_hand[None], q_hand[None]
    assert planner.screen(poses, hands, push=0.15 * direction).feasible.tolist() == [True]
    result = planner.screen(poses, hands, push=1.5 * direction)  # 1.5 m: past the Panda's reach
    assert result.feasible.tolist() == [False]
    assert result.reasons == ["push runs out of reach"]


def test_push_segment_is_checked_with_the_object_where_the_push_has_carried_it(box, scene, planner, monkeypatch):
    T_world_hand, q_hand = spatula_pre_contact(box)
    direction = push_frame()[:3, 0]
    start = scene.object.pose()[:3, 3].copy()
    carried = []
    check = scene.collisions

    def recording(*args, **kwargs):
        carried.append(np.dot(scene.object.pose()[:3, 3] - start, direction))
        return check(*args, **kwargs)

    monkeypatch.setattr(scene, "collisions", recording)
    q_pre = planner.ik.solve_hand_poses(T_world_hand).q[0]
    line = planner._cartesian(q_pre, T_world_hand, 0.15 * direction, q_hand, "push", carry_object=True)
    assert len(carried) == len(line) == 16  # the start and 15 waypoints 1 cm apart
    assert np.allclose(carried, np.linspace(0.0, 0.15, 16), atol=1e-6)
    assert np.allclose(scene.object.pose()[:3, 3], start, atol=1e-9)  # put back afterwards


def test_approaches_are_tried_in_order_until_one_works(box, scene):
    T_world_hand, q_hand = spatula_pre_contact(box)
    direction = push_frame()[:3, 0]
    unreachable = (5.0, 0.05)  # 5 m behind the object
    fallback = MotionPlanner(scene, settings=MotionSettings(approaches=(unreachable, (0.05, 0.05))))
    plan = fallback.plan_push(T_world_hand, q_hand, direction, 0.15, return_home=False)
    assert [s.label for s in plan.segments] == ["approach", "push", "retreat"]
    only_unreachable = MotionPlanner(scene, settings=MotionSettings(approaches=(unreachable,)))
    with pytest.raises(PlanningError) as error:
        only_unreachable.plan_push(T_world_hand, q_hand, direction, 0.15, return_home=False)
    assert error.value.reason == "no IK solution" and "approach segment" in error.value.detail


def test_a_pose_no_approach_leads_to_names_why_each_way_in_failed(box, scene):
    """Out of reach from behind and blocked from above (here: "above" 10 cm down, through the table)."""
    T_world_hand, q_hand = spatula_pre_contact(box)
    blocked = MotionPlanner(scene, settings=MotionSettings(approaches=((5.0, 0.05), (0.0, -0.10))))
    with pytest.raises(PlanningError) as error:
        blocked.plan_push(T_world_hand, q_hand, push_frame()[:3, 0], 0.15, return_home=False)
    assert error.value.reason.startswith("no approach (from behind: no IK solution; from above: ")
    assert "collision" in error.value.reason and "table" in error.value.detail
    assert error.value.detail.startswith("from behind: approach segment: the arm cannot follow")


def test_a_hand_too_near_the_object_6_cm_above_its_pose_comes_straight_down_from_higher(box, scene):
    """The spatula pose behind the box with no way in from behind (5 m back): 6 cm above the pose a finger is
    within the free-space clearance of the box; the shipped ways down from higher up plan."""
    T_world_hand, q_hand = spatula_pre_contact(box)
    direction = push_frame()[:3, 0]
    from_6_cm = MotionPlanner(scene, settings=MotionSettings(approaches=((5.0, 0.05), (0.0, 0.06))))
    with pytest.raises(PlanningError) as error:
        from_6_cm.plan_push(T_world_hand, q_hand, direction, 0.15, return_home=False)
    assert "from above: approach configuration in collision" in error.value.reason and "vs object" in error.value.detail
    straight_down = tuple(a for a in MotionSettings().approaches if a[0] == 0.0)
    assert max(lift for _, lift in straight_down) > 0.06
    shipped = MotionPlanner(scene, settings=MotionSettings(approaches=((5.0, 0.05), *straight_down)))
    plan = shipped.plan_push(T_world_hand, q_hand, direction, 0.15, return_home=False)
    assert [s.label for s in plan.segments] == ["approach", "push", "retreat"]


def test_target_inside_the_table_is_infeasible_with_a_clear_reason(box, planner):
    T_world_hand, q_hand = spatula_pre_contact(box)
    T_world_hand[2, 3] = -0.05  # the hand base 5 cm below the table top
    with pytest.raises(PlanningError) as error:
        planner.plan_push(T_world_hand, q_hand, push_frame()[:3, 0], 0.15)
    assert error.value.reason == "pre-contact pose in collision"
    assert "vs table" in str(error.value)


def test_unreachable_target_reports_no_ik_solution(box, planner):
    T_world_hand, q_hand = spatula_pre_contact(box)
    T_world_hand[0, 3] = 2.0
    with pytest.raises(PlanningError) as error:
        planner.plan_push(T_world_hand, q_hand, push_frame()[:3, 0], 0.15)
    assert error.value.reason == "no IK solution"


# ------------------------------------------------------------------------------------- multi-step


def test_rrt_star_object_path_goes_around_a_circular_obstacle():
    start, goal, obstacle, object_radius = (0.5, -0.3), (0.5, 0.3), (0.5, 0.0, 0.08), 0.05
    path = plan_object_path(start, goal, [obstacle], object_radius_m=object_radius, margin_m=0.02)
    waypoints = path.waypoints
    assert np.allclose(waypoints[0], start) and np.allclose(waypoints[-1], goal)
    dense = interpolate_path(waypoints, 0.001)
    clearance = np.linalg.norm(dense - np.array(obstacle[:2]), axis=1) - obstacle[2]
    assert clearance.min() > object_radius
    assert path.length_m > 0.6  # the straight line through the obstacle is 0.6 m
    pushes = split_into_pushes(waypoints, 0.2)
    lengths = [np.linalg.norm(b - a) for a, b in pushes]
    assert max(lengths) <= 0.2 + 1e-9
    assert np.allclose(pushes[0][0], start) and np.allclose(pushes[-1][1], goal)


def test_object_path_is_the_same_for_the_same_seed_whatever_ran_before():
    args = ((0.5, -0.3), (0.5, 0.3), [(0.5, 0.0, 0.08)])
    first = plan_object_path(*args, object_radius_m=0.05, seed=3).waypoints
    plan_object_path(*args, object_radius_m=0.05, seed=4)  # draws from OMPL's random numbers in between
    assert np.array_equal(plan_object_path(*args, object_radius_m=0.05, seed=3).waypoints, first)


def test_object_path_refuses_a_goal_inside_an_obstacle():
    with pytest.raises(PlanningError) as error:
        plan_object_path((0.5, -0.3), (0.5, 0.02), [(0.5, 0.0, 0.08)], object_radius_m=0.05)
    assert error.value.reason == "goal blocked"


def test_multi_step_pushes_replan_from_the_observed_position_until_the_goal():
    start, goal, obstacle, object_radius = np.array([0.5, -0.3]), np.array([0.5, 0.3]), (0.5, 0.0, 0.06), 0.05
    pushes = []

    def imperfect_push(from_xy: np.ndarray, to_xy: np.ndarray) -> np.ndarray:
        """Falls 10% short and drifts 1 cm to the right of the push, like a real push might."""
        step = to_xy - from_xy
        right = np.array([step[1], -step[0]]) / np.linalg.norm(step)
        pushes.append((from_xy, to_xy))
        return from_xy + 0.9 * step + 0.01 * right

    result = push_along_path(start, goal, [obstacle], imperfect_push, object_radius_m=object_radius,
                             max_push_m=0.2, goal_tolerance_m=0.03, max_steps=12)
    assert result.success, result.message
    assert np.linalg.norm(result.positions[-1] - goal) <= 0.03
    assert all(np.linalg.norm(b - a) <= 0.2 + 1e-9 for a, b in pushes)
    # Every push started where the previous one was observed to end (re-planning, not the old path).
    assert all(np.allclose(a, observed) for (a, _), observed in zip(pushes, result.positions[:-1], strict=True))
    travelled = interpolate_path(np.array(result.positions), 0.001)
    assert (np.linalg.norm(travelled - np.array(obstacle[:2]), axis=1) - obstacle[2]).min() > object_radius


def test_a_push_the_arm_cannot_make_is_turned_and_the_object_still_reaches_the_goal():
    """An arm that cannot push within 10 deg of +y (say, out of reach): the turned pushes get the object there."""
    start, goal, obstacle, object_radius = np.array([0.5, -0.3]), np.array([0.5, 0.3]), (0.62, 0.0, 0.04), 0.05
    refused, made = [], []

    def arm(from_xy: np.ndarray, to_xy: np.ndarray) -> np.ndarray:
        step = to_xy - from_xy
        angle = math.degrees(math.atan2(step[1], step[0]))
        if abs(angle - 90.0) < 10.0:
            refused.append(angle)
            raise DirectionInfeasible(RuntimeError("no IK solution"))
        made.append(angle)
        return to_xy

    result = push_along_path(start, goal, [obstacle], arm, object_radius_m=object_radius, max_push_m=0.2,
                             goal_tolerance_m=0.03, max_steps=12)
    assert result.success, result.message
    assert refused and len(made) == len(result.turns_deg) == len(result.positions) - 1
    assert all(abs(turn) in (15.0, 30.0) for turn in result.turns_deg[:1])  # the straight path's push was refused
    travelled = interpolate_path(np.array(result.positions), 0.001)
    assert (np.linalg.norm(travelled - np.array(obstacle[:2]), axis=1) - obstacle[2]).min() > object_radius


def test_turned_pushes_never_cut_into_an_obstacle_and_the_first_refusal_is_raised_when_none_can_be_made():
    start, target, obstacle = np.array([0.5, -0.2]), np.array([0.5, -0.05]), (0.62, -0.1, 0.04)
    kept = dict(turned_pushes(start, target, [obstacle], object_radius_m=0.05, margin_m=0.02))
    assert set(kept) == {15.0, 30.0}  # turned clockwise (negative) the push runs into the obstacle on its right
    for end in kept.values():
        assert np.isclose(np.linalg.norm(end - start), 0.15)
    refusals = []

    def nothing_reachable(from_xy, to_xy):
        refusals.append(DirectionInfeasible(RuntimeError(f"no IK toward {to_xy}")))
        raise refusals[-1]

    with pytest.raises(DirectionInfeasible) as error:
        push_along_path(start, (0.5, 0.2), [], nothing_reachable, object_radius_m=0.05)
    assert error.value is refusals[0] and error.value.turns_tried == [15.0, -15.0, 30.0, -30.0]


def test_the_next_push_skips_a_corner_it_can_cut_and_keeps_one_that_passes_an_obstacle():
    corner_near_start = np.array([[0.0, 0.0], [0.0, 0.015], [0.10, 0.015], [0.30, 0.015]])
    target = next_push_target(corner_near_start, [], object_radius_m=0.05, margin_m=0.08, max_push_m=0.15)
    assert np.allclose(target, [0.10, 0.015])  # one push of 0.10 m instead of 0.015 m, then 0.10 m
    corner = np.array([[0.0, 0.0], [0.0, 0.05], [0.10, 0.05]])
    inside_the_corner = (0.035, 0.015, 0.001)  # the path keeps 3.4 cm from it, the straight line to its end 0.1 cm
    kept = next_push_target(corner, [inside_the_corner], object_radius_m=0.01, margin_m=0.02, max_push_m=0.15)
    assert np.allclose(kept, [0.0, 0.05])
    long_edge = np.array([[0.0, 0.0], [0.4, 0.0]])
    assert np.allclose(next_push_target(long_edge, [], object_radius_m=0.05, margin_m=0.08, max_push_m=0.15),
                       [0.4 / 3, 0.0])


def test_joint_paths_keep_the_hand_inside_the_workspace_box_the_robot_enforces(scene):
    """A straight joint-space edge whose hand bulges 5 cm out of a box around its two ends: with the box the
    path goes around inside it (the robot bridge would refuse the straight one), and a start outside the box is
    refused by name."""
    limits = RobotLimits.for_robot("panda", "allegro")
    home = limits.arm.home.double().numpy()
    goal = home + np.array([-0.95, -0.53, 0.0, 0.49, 0.0, 0.0, 0.0])  # shoulder turned, arm raised
    ends = limits.tool_points(np.stack([home, goal])).reshape(-1, 3)
    box = WorkspaceBox(tuple(ends.min(axis=0) - 0.03), tuple(ends.max(axis=0) + 0.03))
    straight = home + np.linspace(0.0, 1.0, 100)[:, None] * (goal - home)
    assert not np.all(box.contains(limits.tool_points(straight)))
    q_hand, planner = np.zeros(16), MotionPlanner(scene, workspace=box)
    path = planner.plan_joint_path(home, goal, q_hand)
    dense = np.concatenate([a + np.linspace(0.0, 1.0, 50)[:, None] * (b - a)
                            for a, b in zip(path[:-1], path[1:], strict=True)])
    assert np.all(box.contains(limits.tool_points(dense)))
    turned_away = home - np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    with pytest.raises(PlanningError) as error:
        planner.plan_joint_path(turned_away, goal, q_hand)
    assert error.value.reason == "start configuration outside the workspace box"


def test_a_candidate_raised_out_of_the_table_is_the_same_pose_in_the_direction_frame_and_the_world(box):
    push = Push(box_pose(box), direction_xy(125.0), 0.2)  # D turned against the world: z is shared all the same
    _, q_hand = spatula_pre_contact(box)
    rng = np.random.default_rng(0)
    poses_d = np.concatenate([rng.uniform(-0.1, 0.1, (3, 3)), np.repeat(matrix_to_r6(np.eye(3))[None], 3, axis=0),
                              np.repeat(q_hand[None], 3, axis=0)], axis=1)
    hand = load_hand("allegro")
    raised = Candidates.in_frame(poses_d.copy(), push, hand)
    raised.raise_poses(np.array([0, 2]), np.array([0.006, 0.011]))
    lifted_d = poses_d.copy()
    lifted_d[[0, 2], 2] += [0.006, 0.011]
    expected = Candidates.in_frame(lifted_d, push, hand)
    for got, want in ((raised.poses_d, expected.poses_d), (raised.poses_world, expected.poses_world),
                      (raised.T_world_hand, expected.T_world_hand)):
        np.testing.assert_allclose(got, want, atol=1e-12)

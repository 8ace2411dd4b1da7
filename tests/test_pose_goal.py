"""Push to a pose: a goal point with a goal yaw (`PushRequest.goal_yaw_deg`, `gd2p push --goal X Y --goal-yaw DEG`).

The request and its validation, the one judge with a yaw tolerance, the ranking's yaw term, the multi-step loop's
turning pushes, the hand poses beside the centre of mass that turn the object, and the goals refused before any
motion.
"""
from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from pydantic import ValidationError

from shared.contracts.messages import ObjectPose, ObjectRef, PlannerOptions, PushRequest
from shared.frames import yaw_rotation
from shared.world.push_outcome import YawGoal, judge_push, object_pose

BOX = "proc-box-013"  # 13.9 x 4.6 x 7.5 cm; rests as modelled (its rest rotation is the identity)


def _at(x: float, y: float, yaw_deg: float = 0.0, z: float = 0.0375) -> np.ndarray:
    """T_world_O of an object standing as modelled at (x, y), turned `yaw_deg` about world z."""
    T = np.eye(4)
    T[:3, :3] = yaw_rotation(math.radians(yaw_deg))
    T[:3, 3] = (x, y, z)
    return T


# ------------------------------------------------------------------------------- the request


def test_a_pose_goal_request_survives_the_wire():
    from shared.contracts.codec import decode, encode

    request = PushRequest(object=ObjectRef(library_id=BOX), goal_xy=(0.5, -0.15), goal_yaw_deg=45.0)
    payload, encoding = encode(request)
    decoded = decode(payload, encoding)
    assert decoded == request and decoded.goal_yaw_deg == 45.0
    plain = {"object": {"library_id": BOX}, "goal_xy": [0.5, -0.15], "goal_yaw_deg": -30.0}
    assert decode(msgpack.packb(plain), "application/msgpack;PushRequest").goal_yaw_deg == -30.0


def test_a_goal_yaw_needs_a_goal_point_and_a_finite_angle():
    with pytest.raises(ValidationError, match="goal_yaw_deg needs goal_xy"):
        PushRequest(object=ObjectRef(library_id=BOX), direction_deg=90.0, goal_yaw_deg=30.0)
    with pytest.raises(ValidationError, match="goal_yaw_deg"):
        PushRequest(object=ObjectRef(library_id=BOX), goal_xy=(0.5, 0.0), goal_yaw_deg=math.inf)
    assert PushRequest(object=ObjectRef(library_id=BOX), goal_xy=(0.5, 0.0)).goal_yaw_deg is None


# ------------------------------------------------------------------------------- the judge


def test_the_judge_of_a_pose_goal_holds_the_yaw_to_15_deg_and_the_position_to_2_cm():
    start, goal = _at(0.5, 0.15), np.array([0.5, -0.15])
    yaw_goal = YawGoal(90.0)

    def judged(x, y, yaw_deg):
        return judge_push(start, goal, object_pose(_at(x, y, yaw_deg)), max_rotation_deg=None, yaw_goal=yaw_goal)

    assert judged(0.5, -0.15, 100.0).success and judged(0.5, -0.15, 100.0).yaw_error_deg == pytest.approx(10.0)
    assert not judged(0.5, -0.15, 110.0).success and judged(0.5, -0.15, 110.0).yaw_error_deg == pytest.approx(20.0)
    assert judged(0.5, -0.135, 90.0).success  # 1.5 cm off
    assert not judged(0.5, -0.125, 90.0).success  # 2.5 cm off: a point goal's 3 cm would pass it
    assert judge_push(start, goal, object_pose(_at(0.5, -0.125, 0.0)), max_rotation_deg=None).success
    assert judge_push(start, goal, object_pose(_at(0.5, -0.125, 0.0)), max_rotation_deg=None).yaw_error_deg is None
    # The yaw error takes the short way round, and a turn of 90 deg from the start is what this goal asks.
    assert judged(0.5, -0.15, -265.0).success and judged(0.5, -0.15, -265.0).yaw_error_deg == pytest.approx(5.0)


def test_a_goal_yaw_is_read_from_the_resting_pose_not_from_the_principal_axes():
    """A mug rests with its frame O's x axis upright: O's own Euler yaw swings wildly as the pose tilts a degree,
    the yaw of its resting pose turned about world z does not."""
    from shared.world.objects import load_object
    from shared.world.push_outcome import resting_rotation

    mug = load_object("pb-mug")
    rest = mug.default_pose.rotation
    T = _at(0.5, 0.0) @ mug.T_D_O(yaw_rad=math.radians(30.0))
    tilted = T.copy()
    tilted[:3, :3] = T[:3, :3] @ np.array([[1.0, 0.0, 0.0], [0.0, math.cos(0.02), -math.sin(0.02)],
                                            [0.0, math.sin(0.02), math.cos(0.02)]])  # about 1 deg off upright
    assert np.allclose(resting_rotation([p.rotation for p in mug.resting_poses], T[:3, :3]), rest)
    goal = YawGoal(30.0, rest)
    assert goal.error_deg(T[:3, :3]) == pytest.approx(0.0, abs=1e-6)
    assert goal.error_deg(tilted[:3, :3]) < 2.0


# ------------------------------------------------------------------------------- the ranking


def _rollout(final: np.ndarray, rotation_deg: float, position_error_m: float = 0.01):
    """A one-row arm rollout result that left the object at `final`, `rotation_deg` turned from its start."""
    from shared.contracts.messages import ValidationResult

    def one(value, dtype=np.float64):
        return np.array([value], dtype=dtype)

    return ValidationResult(job_id="j", hand="allegro", object_id=BOX, success=one(True, bool),
                            position_error_m=one(position_error_m), rotation_deg=one(rotation_deg),
                            max_tilt_deg=one(2.0), contact_kept=one(True, bool), hand_table_contact=one(False, bool),
                            initial_penetration_m=one(0.0), goal_error_m=one(position_error_m),
                            collision_cost=one(0.0), obstacle_contact=one(False, bool),
                            final_object_poses=[object_pose(final)])


def test_the_ranking_of_a_pose_goal_prefers_the_rollout_ending_at_the_goal_yaw():
    """Equal position, one rollout at the goal yaw (it turned the object 50 deg to get there, past the point
    goal's 45 deg bound), one 40 deg off it (turned 10 deg): with the yaw term the first ranks ahead; without a
    goal yaw the turn bound would put it behind."""
    from shared.planning.ranking import YawTerm, order, score_rollout

    term = YawTerm(YawGoal(50.0), length_m=0.073)
    at_goal_yaw, off_by_40 = _rollout(_at(0.5, 0.0, 50.0), 50.0), _rollout(_at(0.5, 0.0, 10.0), 10.0)
    scores = [score_rollout(off_by_40, -1.0, yaw_term=term), score_rollout(at_goal_yaw, -1.0, yaw_term=term)]
    assert order(scores) == [1, 0]
    assert scores[1].l_goal == pytest.approx(0.01) and scores[0].l_goal == pytest.approx(0.01 + 0.073 * math.radians(40))
    assert order([score_rollout(off_by_40, -1.0), score_rollout(at_goal_yaw, -1.0)]) == [0, 1]


def test_the_prescreen_of_a_pose_goal_keeps_a_floating_push_that_turns_as_asked_though_it_falls_short():
    from types import SimpleNamespace

    from shared.contracts.messages import ValidationResult
    from shared.planning.ranking import YawTerm
    from shared.planning.stages import prescreen_judged

    rows = dict(success=np.array([True, False, False]), position_error_m=np.array([0.005, 0.04, 0.01]),
                rotation_deg=np.array([1.0, 29.0, 2.0]), max_tilt_deg=np.array([1.0, 3.0, 80.0]),
                contact_kept=np.ones(3, bool), hand_table_contact=np.zeros(3, bool), initial_penetration_m=np.zeros(3))
    result = ValidationResult(job_id="j", hand="allegro", object_id=BOX, **rows)
    push = SimpleNamespace(T_world_O=_at(0.5, 0.0))
    goal = YawGoal(30.0)
    standing, miss = prescreen_judged(SimpleNamespace(yaw_goal=goal, yaw_term=YawTerm(goal, 0.146)), push, result)
    assert standing.tolist() == [True, True, False]  # the third toppled
    assert miss[1] < miss[0]  # 4 cm short but turned 29 of the 30 deg asked, against on target and not turned
    point_goal = SimpleNamespace(yaw_goal=None, yaw_term=None)
    passed, error = prescreen_judged(point_goal, push, result)
    assert passed.tolist() == [True, False, False] and np.allclose(error, [0.005, 0.04, 0.01])


# ------------------------------------------------------------------------------- the multi-step loop


def test_an_object_at_the_goal_point_but_off_the_goal_yaw_is_pushed_off_it_and_back_until_the_yaw_is_met():
    """A make-believe push that lands on its target and turns the object 20 deg each time: at the point with the
    yaw still off, the loop pushes it sideways (toward the robot's centre line) and back, until `at_goal`."""
    from shared.planning.multistep import TURNING_PUSH_M, push_along_path

    yaw = [0.0]
    pushes = []

    def turning_push(from_xy, to_xy):
        pushes.append((np.asarray(from_xy), np.asarray(to_xy)))
        yaw[0] += 20.0
        return np.asarray(to_xy, dtype=np.float64)

    def at_goal(xy):
        return bool(np.linalg.norm(xy - (0.5, 0.15)) <= 0.02 and abs(yaw[0] - 60.0) <= 15.0)

    result = push_along_path((0.5, 0.35), (0.5, 0.15), [], turning_push, object_radius_m=0.07, max_push_m=0.2,
                             goal_tolerance_m=0.02, at_goal=at_goal, max_steps=6)
    assert result.success and yaw[0] == 60.0 and len(pushes) == 3
    first_turning = pushes[1][1] - pushes[1][0]
    assert np.allclose(first_turning, (0.0, -TURNING_PUSH_M))  # sideways, toward y = 0 where the robot stands
    assert np.allclose(pushes[2][1], (0.5, 0.15))  # and back to the point
    assert len(result.paths) == len(pushes)


def test_every_push_of_a_pose_goal_is_to_turn_the_object_toward_its_yaw_at_most_30_deg():
    from shared.planning.goals import MAX_TURN_PER_PUSH_DEG, turn_to_make_deg

    assert MAX_TURN_PER_PUSH_DEG == 30.0
    assert turn_to_make_deg(_at(0.5, 0.0), YawGoal(90.0)) == 30.0
    assert turn_to_make_deg(_at(0.5, 0.0), YawGoal(-20.0)) == pytest.approx(-20.0)
    assert turn_to_make_deg(_at(0.5, 0.0, 170.0), YawGoal(-170.0)) == pytest.approx(20.0)  # the short way round
    assert turn_to_make_deg(_at(0.5, 0.0, 90.0), YawGoal(90.0)) == pytest.approx(0.0)  # at the yaw: keep it
    assert turn_to_make_deg(_at(0.5, 0.0), None) is None  # a point goal: no turned poses


def test_a_turned_palm_is_slanted_to_the_edge_it_meets_by_the_turn_and_stays_as_far_behind_the_outline():
    """The spatula pose (palm square to the push) behind the box: to turn the square box 30 deg counterclockwise
    its copy is slanted 30 deg and sits on D's -y side (the side that turns it that way), as far behind the outline
    along its palm normal as the pose was. Behind the box already turned 20 deg, a copy that keeps the yaw lies
    flat on the turned edge (slant 20): a palm square to the push would square the box back."""
    from shared.frames import pose25_to_matrix
    from shared.planning.goals import facing_edge_deg, turning_poses
    from shared.robots.hands import load_hand
    from shared.world.fixed_poses import spatula_pose
    from shared.world.objects import load_object

    hand, box = load_hand("allegro"), load_object(BOX)
    vertices = box.mesh_in_d().vertices  # in D: the centre of mass above its origin
    pose = spatula_pose(hand, vertices)
    T, _ = pose25_to_matrix(pose)
    palm = T[:3, :3] @ hand.palm_normal_base.double().numpy()

    def slant_deg(turned_pose):
        T_turned, _ = pose25_to_matrix(turned_pose)
        normal = T_turned[:3, :3] @ hand.palm_normal_base.double().numpy()
        return math.degrees(math.atan2(normal[1], normal[0]))

    def gap(position, direction):  # how far behind the outline, against `direction`, the hand base stands
        return float(-position @ direction) - float(np.max(vertices @ -direction))

    assert facing_edge_deg(vertices) == pytest.approx(0.0, abs=1e-6)
    [turned] = turning_poses(pose[None], palm[None], vertices, 30.0)
    T_turned, _ = pose25_to_matrix(turned)
    assert slant_deg(turned) == pytest.approx(30.0) and T_turned[1, 3] < T[1, 3] - 0.01
    turned_axis = yaw_rotation(math.radians(30.0))[:, 0]
    assert gap(T_turned[:3, 3], turned_axis) == pytest.approx(gap(T[:3, 3], np.array([1.0, 0.0, 0.0])), abs=1e-9)
    assert np.array_equal(turned[9:], pose[9:])  # the fingers as they were

    box_turned = vertices @ yaw_rotation(math.radians(20.0)).T
    assert facing_edge_deg(box_turned) == pytest.approx(20.0)
    [kept] = turning_poses(pose[None], palm[None], box_turned, 0.0)
    assert slant_deg(kept) == pytest.approx(20.0)
    [steep] = turning_poses(pose[None], palm[None], box_turned, 30.0)
    assert slant_deg(steep) == pytest.approx(45.0)  # 50 deg would slide along the edge


def test_a_turned_copy_is_considered_right_after_its_pose():
    from types import SimpleNamespace

    from shared.planning.candidates import Candidates
    from shared.planning.stages import priority

    k = 3
    l_dir = np.array([-1.0, -1.0, -0.9, -0.87, -0.87, -0.78])  # three poses (two tied), their turned copies
    candidates = Candidates(np.zeros((2 * k, 25)), np.zeros((2 * k, 25)), np.zeros((2 * k, 4, 4)),
                            np.zeros((2 * k, 16)), l_dir, source=np.tile(np.arange(k), 2))
    state = SimpleNamespace(request=PushRequest(object=ObjectRef(library_id=BOX), goal_xy=(0.5, 0.0)), seed=0)
    assert priority(state, candidates).tolist() == [0, 3, 1, 4, 2, 5]
    critic = Candidates(*(getattr(candidates, f) for f in ("poses_d", "poses_world", "T_world_hand", "q_hands",
                                                         "l_dir")), p_success=np.tile([0.2, 0.9, 0.5], 2),
                        source=candidates.source)
    assert priority(state, critic).tolist() == [1, 4, 2, 5, 0, 3]


# ------------------------------------------------------------------------------- refused before any motion


def _never_moves(*_args, **_kwargs):
    raise AssertionError("nothing may be sampled, rolled out or executed for a goal refused up front")


@pytest.mark.parametrize("goal, yaw, object_id, code, says", [
    ((1.48, 0.0), None, BOX, "bad_request", "is off the table"),
    ((0.5, -1.47), 90.0, BOX, "bad_request", "is off the table"),
    ((1.38, 0.0), 90.0, BOX, "infeasible", "out of the robot's reach"),
    ((0.5, -0.15), 90.0, "proc-cylinder-001", "bad_request", "looks the same at every yaw"),
])
def test_a_goal_no_push_can_reach_is_refused_before_the_robot_moves(goal, yaw, object_id, code, says):
    from shared.planning.outcome import PushError
    from shared.planning.pipeline import PushPipeline, PushServices

    pipeline = PushPipeline(PushServices(sample=_never_moves, validate=_never_moves, execute=_never_moves))
    request = PushRequest(object=ObjectRef(library_id=object_id), goal_xy=goal, goal_yaw_deg=yaw,
                          options=PlannerOptions(method="fixed"))
    try:
        with pytest.raises(PushError) as refusal:
            pipeline.run(request)
    finally:
        pipeline.close()
    assert refusal.value.code == code and says in refusal.value.message and not refusal.value.records


@pytest.mark.parametrize("target", [{"direction_deg": 90.0}, {"goal_xy": (0.5, -0.15)}])
def test_an_obstacle_through_the_object_is_refused_before_the_robot_moves(target):
    """The box (4.6 cm wide) stands at the default spot (0.55, 0): a cylinder of 3 cm radius 4 cm beside its centre
    line reaches 1.3 cm into it; one touching its side is a neighbour, planned around."""
    from shared.contracts.messages import CircleObstacle
    from shared.planning.goals import check_obstacles
    from shared.planning.outcome import PushError
    from shared.planning.pipeline import PushPipeline, PushServices

    pipeline = PushPipeline(PushServices(sample=_never_moves, validate=_never_moves, execute=_never_moves))
    request = PushRequest(object=ObjectRef(library_id=BOX), obstacles=[CircleObstacle(x=0.55, y=0.04, radius=0.03)],
                          options=PlannerOptions(method="fixed"), **target)
    try:
        with pytest.raises(PushError) as refusal:
            pipeline.run(request)
    finally:
        pipeline.close()
    assert refusal.value.code == "bad_request" and "obstacle 0" in refusal.value.message
    assert "into the object's footprint" in refusal.value.message and not refusal.value.records
    square = np.array([[-0.02, -0.02], [0.02, -0.02], [0.02, 0.02], [-0.02, 0.02]])
    check_obstacles([CircleObstacle(x=0.05, y=0.0, radius=0.03)], square)  # touching the side: a neighbour
    check_obstacles([CircleObstacle(x=0.05, y=0.05, radius=0.04)], square)  # 2.4 mm short of the corner
    with pytest.raises(PushError, match="reaches 5 mm into"):
        check_obstacles([CircleObstacle(x=0.0, y=-0.045, radius=0.03)], square)


def test_the_reach_bound_holds_the_default_spot_and_not_a_goal_two_metres_out():
    from shared.robots.reach import reach

    panda = reach("panda", "allegro")
    shoulder = panda.shoulder_world(np.eye(4))
    assert np.allclose(shoulder, (0.0, 0.0, 0.333))
    assert 1.0 < panda.radius_m < 1.4  # 0.99 m of links, the 2 cm adapter and mount, a 20 cm open hand
    assert np.linalg.norm(np.array([0.55, 0.0, 0.0]) - shoulder) < panda.radius_m
    assert reach("xarm7", "leap").radius_m < panda.radius_m


# ------------------------------------------------------------------------------- the CLI


def test_gd2p_push_refuses_a_goal_yaw_without_a_goal_point(capsys):
    from cli.main import main

    code = main(["push", "--object", BOX, "--direction-deg", "90", "--goal-yaw", "30", "--connect", "tcp/127.0.0.1:9"])
    err = capsys.readouterr().err
    assert code == 2 and "--goal-yaw is the yaw of a goal pose: give the goal point with --goal X Y" in err
    assert "Traceback" not in err


def test_gd2p_push_sends_the_goal_yaw_and_says_how_far_the_object_ended_from_it():
    import argparse

    from cli.push import build_request, describe, register
    from shared.contracts.messages import ExecutionResult, Plan, PushResponse

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["push", "--object", BOX, "--goal", "0.5", "-0.15", "--goal-yaw", "45"])
    request = build_request(args)
    assert request.goal_xy == (0.5, -0.15) and request.goal_yaw_deg == 45.0
    assert "--goal-yaw DEG" in parser._subparsers._group_actions[0].choices["push"].format_help()
    result = ExecutionResult(final_object_pose=ObjectPose(position=(0.5, -0.15, 0.04)), position_error_m=0.01,
                             rotation_deg=40.0, toppled=False, success=True, yaw_error_deg=5.0)
    plan = Plan(arm="panda", hand="allegro", joint_names=["a"], positions=np.zeros((2, 1)), times_s=np.array([0.0, 1.0]))
    response = PushResponse(request_id=request.id, success=True, chosen_pose=np.zeros(25), chosen_pose_world=np.zeros(25),
                            plan=plan, result=result)
    assert "5.0° from the goal yaw" in describe(response)


# ------------------------------------------------------------------------------- end to end


@pytest.mark.slow
def test_a_box_at_the_goal_point_but_40_deg_off_its_yaw_is_pushed_off_it_and_back_turned_into_the_pose():
    """The simulated robot (in process, the spatula poses as the pose source): the box stands at the goal point,
    its yaw 40 deg short of the goal's. A turning push takes it sideways, the pushes that follow bring it back
    turned by slanted palms, until it is within 2 cm and 15 deg of the pose (about 25 s of CPU)."""
    from evaluation.local_system import LocalRobot, validate_here
    from shared.planning.pipeline import PushPipeline, PushServices
    from shared.planning.stages import PipelineSettings
    from test_push import _box_at, _spatula_poses

    robot = LocalRobot()
    pipeline = PushPipeline(PushServices(sample=_spatula_poses, validate=validate_here, execute=robot.execute),
                            PipelineSettings(max_plans=2, prescreen=0, max_plan_rounds=1))
    request = PushRequest(object=ObjectRef(library_id=BOX), object_pose=object_pose(_box_at(0.5, 0.12)),
                          goal_xy=(0.5, 0.12), goal_yaw_deg=40.0, distance_m=0.13,
                          options=PlannerOptions(k=8, max_steps=6))
    try:
        response = pipeline.run(request).response
    finally:
        pipeline.close()
        robot.close()
    result = response.result
    assert response.success, result
    assert result.position_error_m <= 0.02 and result.yaw_error_deg <= 15.0 and result.rotation_deg > 25.0
    first = np.array(response.steps[0].result.final_object_pose.position[:2])
    assert first[1] < 0.12 - 0.03  # the first push took it off the point, sideways toward the robot's centre line
    assert response.steps[0].score.l_goal > 0.0 and len(response.steps) <= 6


def test_a_pose_trial_whose_capture_shows_too_little_is_refused_as_the_system_refuses_it_not_a_crash():
    """The pose task reads the yaw the system sees from the capture before it asks: a capture too sparse to
    reconstruct (a small object seen from afar) is the system's bad_request, recorded as that trial's error, as the
    paper's task records it, never an exception that stops the evaluation."""
    from evaluation.push_protocol import _seen_yaw
    from shared.planning.outcome import PushError

    sparse = np.random.default_rng(0).uniform([0.39, -0.01, 0.0], [0.41, 0.01, 0.02], size=(30, 3))
    with pytest.raises(PushError) as refused:
        _seen_yaw(ObjectRef(point_cloud=sparse), None)
    assert refused.value.code == "bad_request" and "too few" in refused.value.message

"""Closed-loop pushing: the robot's object tracking, the planner's monitor, stopping, backing out, correcting."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from shared.contracts.messages import (
    ExecutionState,
    ObjectPath,
    ObjectRef,
    Plan,
    PlannerOptions,
    PlanSegment,
    PushRequest,
)
from shared.frames import yaw_rotation
from shared.world.push_outcome import object_pose, pose_matrix

BOX = "proc-box-013"  # as tests/test_push.py


# ------------------------------------------------------------------------------------------ the monitor


def _plan() -> Plan:
    """A 7-joint plan: 2 s of approach, a 4 s push, 2 s of retreat (one waypoint every 0.1 s)."""
    times = np.arange(81) * 0.1
    return Plan(arm="panda", hand="allegro", joint_names=[f"j{i}" for i in range(7)],
                positions=np.outer(times, np.ones(7)) * 0.01, times_s=times,
                segments=[PlanSegment(label="approach", start=0, stop=20), PlanSegment(label="push", start=20, stop=61),
                          PlanSegment(label="retreat", start=61, stop=81)])


def _straight_path() -> ObjectPath:
    """The predicted path: at rest at (0.5, 0) until 2 s, then 5 cm/s along +x until 6 s, then at rest."""
    times = np.arange(1, 161) * 0.05
    x = 0.5 + 0.05 * np.clip(times - 2.0, 0.0, 4.0)
    return ObjectPath(times_s=times, positions=np.stack([x, np.zeros_like(x), np.full_like(x, 0.03)], axis=1),
                      quaternions_xyzw=np.tile([0.0, 0.0, 0.0, 1.0], (len(times), 1)))


def _seen(x: float, y: float = 0.0, yaw_deg: float = 0.0):
    T = np.eye(4)
    T[:3, :3] = yaw_rotation(np.radians(yaw_deg))
    T[:3, 3] = (x, y, 0.03)
    return object_pose(T)


def _monitor(**thresholds):
    from shared.planning.monitor import MonitorThresholds, PushMonitor

    return PushMonitor(_plan(), _straight_path(), np.array([1.0, 0.0]), MonitorThresholds(**thresholds))


def test_an_object_following_its_predicted_path_from_another_start_is_not_stopped():
    monitor = _monitor()
    offset = 0.008  # the object truly stands 8 mm off where the planner was told: displacements still agree
    for t in np.arange(1.0, 8.0, 0.05):
        assert monitor.observe(t, _seen(0.5 + offset + 0.05 * np.clip(t - 2.0, 0.0, 4.0), 0.004)) is None
    assert monitor.stop_reason is None and monitor.observed > 70


@pytest.mark.parametrize("seen_at, says", [
    (lambda t: _seen(0.5 + 0.02 * (t - 2.0)), "behind the predicted path"),  # slipping off the hand: lags
    (lambda t: _seen(0.5 + 0.05 * (t - 2.0), 0.03 * (t - 2.0)), "beside the predicted path"),  # sliding sideways
    (lambda t: _seen(0.5 + 0.05 * (t - 2.0), 0.0, 12.0 * (t - 2.0)), "turned"),  # spinning
])
def test_an_object_straying_from_its_predicted_path_stops_the_push_with_the_reason(seen_at, says):
    monitor = _monitor()
    assert monitor.observe(1.0, _seen(0.5)) is None  # at rest before the push: the reference
    reasons = [monitor.observe(t, seen_at(t)) for t in np.arange(2.0, 6.0, 0.05)]
    stop = next(r for r in reasons if r is not None)
    assert says in stop and monitor.stop_reason == stop
    assert 2.0 < monitor.stop_time_s < 6.0
    assert all(r is None for r in reasons[reasons.index(stop) + 1:])  # one verdict


def test_an_object_turning_less_than_predicted_or_a_little_the_other_way_is_not_stopped():
    from shared.planning.monitor import MonitorThresholds, PushMonitor

    turning = _straight_path()
    times = turning.times_s.to_numpy()
    yaw = np.radians(8.0 * np.clip(times - 2.0, 0.0, 4.0))  # predicted: turning to +32° over the push
    turning = ObjectPath(times_s=times, positions=turning.positions.to_numpy(),
                         quaternions_xyzw=np.stack([np.zeros_like(yaw), np.zeros_like(yaw), np.sin(yaw / 2),
                                                    np.cos(yaw / 2)], axis=1))
    for seen_yaw_per_s in (0.0, -3.0, 10.0):  # straight on; a little the other way; a little further
        monitor = PushMonitor(_plan(), turning, np.array([1.0, 0.0]), MonitorThresholds())
        for t in np.arange(1.0, 6.0, 0.05):
            x = 0.5 + 0.05 * np.clip(t - 2.0, 0.0, 4.0)
            assert monitor.observe(t, _seen(x, 0.0, seen_yaw_per_s * max(t - 2.0, 0.0))) is None
    monitor = PushMonitor(_plan(), turning, np.array([1.0, 0.0]), MonitorThresholds())
    reasons = [monitor.observe(t, _seen(0.5 + 0.05 * max(t - 2.0, 0.0), 0.0, -18.0 * max(t - 2.0, 0.0)))
               for t in np.arange(1.0, 6.0, 0.05)]
    assert any(r and "turned" in r for r in reasons)  # the other way and further than predicted: stopped


def test_the_monitor_watches_only_the_push_itself():
    monitor = _monitor()
    assert monitor.observe(0.5, _seen(0.5)) is None
    assert monitor.observe(1.5, _seen(0.6)) is None  # before the push: nothing to compare yet
    assert monitor.observe(7.0, _seen(0.9)) is None  # after it: the hand backs off, stopping gains nothing
    assert monitor.observed == 0


def test_a_state_repeating_the_last_tracked_pose_is_not_compared_again():
    monitor = _monitor()

    def state(t: float, x: float) -> ExecutionState:
        return ExecutionState(stamp=0.0, joint_names=[], positions=np.zeros(0), velocities=np.zeros(0),
                              object_pose=_seen(x), status="executing", plan_time_s=t)

    monitor.observe_state(state(1.0, 0.5))
    monitor.observe_state(state(2.5, 0.525))
    monitor.observe_state(state(2.52, 0.525))  # the tracker's frame repeated in the next state
    assert monitor.observed == 1
    no_time = state(3.0, 0.55).model_copy(update={"plan_time_s": None})
    assert monitor.observe_state(no_time) is None and monitor.observed == 1


def test_a_lost_track_during_the_push_stops_it_but_not_before_or_after_it():
    def lost(t: float) -> ExecutionState:
        return ExecutionState(stamp=0.0, joint_names=[], positions=np.zeros(0), velocities=np.zeros(0),
                              object_lost="3 object points, 30 needed", status="executing", plan_time_s=t)

    monitor = _monitor()
    assert monitor.observe_state(lost(1.0)) is None  # the approach: the hand may hide the object, it is not pushed
    assert monitor.observe(1.5, _seen(0.5)) is None
    reason = monitor.observe_state(lost(3.0))
    assert reason is not None and "lost the object (3 object points, 30 needed)" in reason
    assert monitor.stop_time_s == 3.0
    after = _monitor()
    assert after.observe_state(lost(7.0)) is None  # the retreat: stopping gains nothing


def test_backing_out_retraces_the_plan_from_where_the_robot_stopped_to_its_start():
    from shared.planning.monitor import BACK_OUT_LEAD_S, backed_out

    plan = _plan()
    q_now = np.full(7, 0.0352)  # stopped a little behind the command at 3.55 s
    back = backed_out(plan, 3.55, q_now, np.full(7, -1.0), np.full(7, 1.0))
    positions, times = back.positions.to_numpy(), back.times_s.to_numpy()
    assert np.allclose(positions[0], q_now) and np.allclose(positions[-1], plan.positions.to_numpy()[0])
    assert np.all(np.diff(times) > 0) and times[1] >= BACK_OUT_LEAD_S
    # At the plan's own pace: the way back takes as long as the way there did.
    assert times[-1] == pytest.approx(3.55)
    assert [s.label for s in back.segments] == ["retreat"]
    # A finger pressed past its limit by the object: the way back starts at the limit, not beyond it.
    pressed = q_now.copy()
    pressed[6] = -1.37
    assert -1.0 < backed_out(plan, 3.55, pressed, np.full(7, -1.0), np.full(7, 1.0)).positions.to_numpy()[0, 6] < -0.999


def test_a_plan_may_start_at_the_limit_a_pressed_joint_stands_past_but_not_beyond_it():
    from shared.contracts.messages import ExecutionCommand
    from shared.execution.executor import EStopLatch, Executor, LocalLease
    from shared.execution.robots.sim.config import SimConfig
    from shared.execution.robots.sim.robot import SimRobot

    with SimRobot(SimConfig("panda", "allegro")) as robot:
        limits = robot.limits
        q = robot.observe().positions
        k = len(q) - 1  # a finger joint, pressed 0.3 rad past its lower limit
        q[k] = limits.lower[k] - 0.3
        robot.scene.set_configuration(q[:7], q[7:])
        executor = Executor("panda", "allegro", [robot], EStopLatch())

        def plan_from(first: np.ndarray) -> Plan:
            return Plan(arm="panda", hand="allegro", joint_names=list(robot.joint_names),
                        positions=np.stack([first, first]), times_s=np.array([0.0, 0.5]))

        at_limit = np.clip(q, limits.lower, limits.upper)
        state = executor.execute(ExecutionCommand(plan=plan_from(at_limit), lease_token="t"), LocalLease())
        assert state.status == "done", state.message
        robot.scene.set_configuration(q[:7], q[7:])
        beyond = executor.execute(ExecutionCommand(plan=plan_from(q), lease_token="t"), LocalLease())
        assert beyond.status == "refused" and "limit" in beyond.message


# ------------------------------------------------------------------------------------------ the tracker


def test_a_trial_record_says_how_far_the_object_truly_turned_while_the_tracker_had_lost_it():
    """The judge's comparison of the tracked frames with the truth: a tracker that refuses registrations as turning
    too fast is wrong where the object truly turned that far; the record says how far it did."""
    from evaluation.local_system import TrackingErrors

    def at(yaw_deg: float, x: float = 0.4):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = yaw_rotation(np.radians(yaw_deg)), (x, 0.0, 0.03)
        return object_pose(T)

    errors = TrackingErrors()
    errors.start_push()
    errors.add(at(0.0, 0.402), at(0.0))  # seen, 2 mm off
    errors.add(None, at(12.0))  # lost while it turns
    errors.add(None, at(27.0))
    errors.add(at(31.0), at(30.0))  # seen again, 1 degree off
    errors.start_push()
    errors.add(at(30.0), at(30.0))
    first, second = errors.summary()
    assert (first["frames"], first["lost"]) == (4, 2)
    assert first["lost_true_turn_deg"] == pytest.approx(27.0, abs=0.1)
    assert first["worst_mm"] == pytest.approx(2.0) and first["worst_deg"] == pytest.approx(1.0, abs=0.01)
    assert "lost_true_turn_deg" not in second  # nothing lost


def test_the_simulated_tracker_reports_the_pose_late_and_noisy_and_repeats_with_its_seed():
    from shared.execution.robots.sim.tracker import SimTracker, TrackerConfig

    tracker = SimTracker(TrackerConfig(position_sigma_m=0.002, yaw_sigma_deg=1.0), seed=3)
    poses = [np.eye(4) for _ in range(400)]
    for i, T in enumerate(poses):
        T[0, 3] = 0.01 * i
    reported = [pose_matrix(tracker.frame(T)) for T in poses]
    errors = np.array([reported[i][:3, 3] - poses[i - 1][:3, 3] for i in range(1, 400)])  # one frame late
    assert 0.0015 < errors.std() < 0.0025 and abs(errors.mean()) < 0.0005
    tracker.reset(3)
    assert np.allclose(pose_matrix(tracker.frame(poses[0])), reported[0])
    exact = SimTracker(TrackerConfig(position_sigma_m=0.0, yaw_sigma_deg=0.0, latency_frames=0))
    assert np.allclose(pose_matrix(exact.frame(poses[5])), poses[5])
    with pytest.raises(ValueError, match="rate_hz"):
        TrackerConfig(rate_hz=0.0)


def test_the_simulated_robot_publishes_tracked_poses_at_the_tracker_rate_with_the_plan_time():
    from shared.execution.robot import JointTrajectory
    from shared.execution.robots.sim.config import SimConfig
    from shared.execution.robots.sim.robot import SimRobot, TrueWorld

    tracks, states = [], []
    robot = SimRobot(SimConfig("panda", "allegro", tracking="truth"), publish=states.append)
    robot.track = tracks.append
    with robot:
        T_true = np.eye(4)
        T_true[:3, 3] = (0.5, 0.3, 0.0)
        from shared.world.objects import load_object

        T_true = T_true @ load_object(BOX).T_D_O()
        robot.reset_world(TrueWorld(ObjectRef(library_id=BOX), T_true, tracker_seed=1))
        q = robot.observe().positions
        trajectory = JointTrajectory(robot.joint_names, np.stack([q, q]), np.array([0.0, 2.0]))
        robot.send(trajectory, realtime_factor=1000.0, command_id="c1")
        true = pose_matrix(robot.true_object_pose())
        seen = pose_matrix(robot.observe().object_pose)
        # Observing draws no noise: the frames repeat however often (and from whichever thread) it is called.
        assert np.array_equal(pose_matrix(robot.observe().object_pose), seen)
    duration = 2.0 + robot.params.arm_command_latency_s + robot.params.arm_settle_s
    assert abs(len(tracks) - duration * 20.0) <= 2  # 20 Hz of robot time
    assert all(t.command_id == "c1" and t.source == "sim-tracker" for t in tracks)
    assert np.all(np.diff([t.plan_time_s for t in tracks]) > 0)
    assert all(s.plan_time_s is not None and s.object_pose is not None for s in states)
    # What the robot reports is the tracker's: near the truth, never exactly it.
    assert 0 < np.linalg.norm(seen[:3, 3] - true[:3, 3]) < 0.02
    assert np.allclose(true[:3, 3], T_true[:3, 3], atol=0.002)


# ------------------------------------------------------------------------------------------ closed loop, end to end


def _box_at(x: float, y: float) -> np.ndarray:
    from shared.world.objects import load_object

    T = np.eye(4)
    T[:3, 3] = (x, y, 0.0)
    return T @ load_object(BOX).T_D_O()


def _push_with_a_mid_push_slip(closed_loop: bool):
    """A push of the box along +y whose object slides 5 cm sideways (+x) once it has moved 4 cm: a slip the
    planner's rollout did not predict. The response, the robot's joints after each executed command."""
    from evaluation.local_system import LocalRobot, validate_here
    from shared.planning.pipeline import PushPipeline, PushServices
    from shared.planning.stages import PipelineSettings
    from tests.test_push import _spatula_poses

    start = _box_at(0.5, 0.0)
    slipped = []
    joints_after = []

    class SlippingRobot(LocalRobot):
        def _on_state(self, robot, state):
            if not slipped:
                T = pose_matrix(robot.true_object_pose())
                if T[1, 3] - start[1, 3] > 0.04:
                    T[0, 3] += 0.05
                    robot.scene.object.reset_pose(T)
                    slipped.append(T)
            super()._on_state(robot, state)

        def execute(self, plan, world, cancel=None, monitor=None):
            execution = super().execute(plan, world, cancel, monitor)
            joints_after.append((plan, execution.final.positions.to_numpy()))
            return execution

    robot = SlippingRobot(tracking="truth")  # the slip is a teleport: an image tracker may lose it (tested apart)
    pipeline = PushPipeline(PushServices(sample=_spatula_poses, validate=validate_here, execute=robot.execute),
                            PipelineSettings(max_plans=2, prescreen=0, max_plan_rounds=1))
    try:
        outcome = pipeline.run(PushRequest(object=ObjectRef(library_id=BOX), object_pose=object_pose(start),
                                           direction_deg=90.0, options=PlannerOptions(k=8, corrections=1, closed_loop=closed_loop)))
        return outcome.response, joints_after, slipped
    finally:
        pipeline.close()
        robot.close()


def test_a_push_whose_object_slips_sideways_is_stopped_backed_out_and_corrected():
    response, commands, slipped = _push_with_a_mid_push_slip(closed_loop=True)
    assert slipped
    first = response.steps[0]
    assert first.stopped is not None and "beside the predicted path" in first.stopped
    assert response.notes and response.notes[0].startswith("push 1 stopped: ")
    # The robot backed out the way it came: the second command ends where the first plan started.
    (push_plan, _), (back_plan, back_end) = commands[0], commands[1]
    assert [s.label for s in back_plan.segments] == ["retreat"]
    assert np.allclose(back_end, push_plan.positions.to_numpy()[0], atol=0.02)
    # The stopped push left the object short of the target; the correction pushed it from where it was seen.
    assert len(response.steps) == 2 and response.steps[1].reason.startswith("correction 1: push 1 was stopped with")
    assert first.result.position_error_m > 0.03


def test_the_same_slip_open_loop_runs_the_push_to_its_end():
    response, commands, slipped = _push_with_a_mid_push_slip(closed_loop=False)
    assert slipped and response.steps[0].stopped is None and not response.notes[:1] == ["push 1 stopped"]
    assert all(s.stopped is None for s in response.steps)
    assert [s.label for s in commands[0][0].segments] == ["approach", "push", "retreat"]


def test_a_turn_no_camera_can_see_neither_stops_a_push_nor_counts_against_it():
    """A standing can's turn about its axis is the tracker's guess: the monitor does not stop on it, and the
    planner judges the push by position and uprightness; a box's turn it does see."""
    from shared.planning.monitor import MonitorThresholds, PushMonitor
    from shared.world.objects import load_object
    from shared.world.push_outcome import turn_observable

    up = np.array([0.0, 0.0, 1.0])
    can = trimesh.creation.cylinder(radius=0.03, height=0.12, sections=64)
    assert not turn_observable(can, up) and not turn_observable(trimesh.creation.icosphere(radius=0.04), up)
    assert turn_observable(trimesh.creation.box((0.1, 0.05, 0.08)), up)
    assert turn_observable(can, np.array([1.0, 0.0, 0.0]))  # the same can lying down: its roll shows
    box = load_object(BOX)
    assert turn_observable(box.mesh, box.T_D_O()[:3, :3].T @ up)
    blind = PushMonitor(_plan(), _straight_path(), np.array([1.0, 0.0]), MonitorThresholds(), watch_turn=False)
    seeing = PushMonitor(_plan(), _straight_path(), np.array([1.0, 0.0]), MonitorThresholds())
    for monitor in (blind, seeing):
        monitor.observe(1.5, _seen(0.5))
    assert blind.observe(3.0, _seen(0.55, yaw_deg=60.0)) is None
    assert "turned" in (seeing.observe(3.0, _seen(0.55, yaw_deg=60.0)) or "")


def test_an_object_the_cameras_lose_mid_push_stops_it_and_the_robot_backs_out():
    """Mid-push the object vanishes from every camera (carried off the table): the image tracker reports it lost,
    the monitor stops the push on it, the robot backs out the way it came, and the request answers `lost` instead
    of judging or correcting a pose nobody saw."""
    from evaluation.local_system import LocalRobot, validate_here
    from shared.planning.outcome import PushError
    from shared.planning.pipeline import PushPipeline, PushServices
    from shared.planning.stages import PipelineSettings
    from tests.test_push import _spatula_poses

    start = _box_at(0.5, 0.0)
    carried: list[bool] = []
    commands = []

    class VanishingRobot(LocalRobot):
        def _on_state(self, robot, state):
            if not carried and pose_matrix(robot.true_object_pose())[1, 3] - start[1, 3] > 0.03:
                gone = np.eye(4)
                gone[:3, 3] = (3.0, 3.0, 0.5)  # far outside every camera's view
                robot.scene.object.reset_pose(gone)
                carried.append(True)
            super()._on_state(robot, state)

        def execute(self, plan, world, cancel=None, monitor=None):
            execution = super().execute(plan, world, cancel, monitor)
            commands.append(([s.label for s in plan.segments], execution.final))
            return execution

    robot = VanishingRobot()  # the default: the image tracker
    pipeline = PushPipeline(PushServices(sample=_spatula_poses, validate=validate_here, execute=robot.execute),
                            PipelineSettings(max_plans=2, prescreen=0, max_plan_rounds=1))
    try:
        with pytest.raises(PushError) as raised:
            pipeline.run(PushRequest(object=ObjectRef(library_id=BOX), object_pose=object_pose(start),
                                     direction_deg=90.0, options=PlannerOptions(k=8, corrections=1)))
    finally:
        pipeline.close()
        robot.close()
    assert carried and raised.value.code == "lost", raised.value.message
    (push_labels, stopped), (back_labels, back) = commands
    assert push_labels == ["approach", "push", "retreat"] and stopped.status == "stopped"
    assert back_labels == ["retreat"] and back.object_pose is None and back.object_lost


def test_a_finger_pushed_far_off_its_command_backs_out_within_its_velocity_limit():
    """A compliant thumb the toppling object pushed a radian off the plan: the way back's first step is slowed so
    no joint exceeds half its limit (the bridge refused a 0.1 s step at 11 rad/s in MuJoCo), then follows the
    plan's pace."""
    from shared.planning.monitor import BACK_OUT_LEAD_S, BACK_OUT_VELOCITY_SHARE, backed_out

    plan = _plan()
    q_now = np.full(7, 0.0352)
    q_now[6] = -0.95  # the plan has it near 0.035
    velocity = np.full(7, 5.0)
    back = backed_out(plan, 3.55, q_now, np.full(7, -1.0), np.full(7, 1.0), velocity)
    positions, times = back.positions.to_numpy(), back.times_s.to_numpy()
    speeds = np.abs(np.diff(positions, axis=0)) / np.diff(times)[:, None]
    assert speeds[0].max() <= BACK_OUT_VELOCITY_SHARE * 5.0 + 1e-9 and times[1] > BACK_OUT_LEAD_S
    unhurried = backed_out(plan, 3.55, q_now, np.full(7, -1.0), np.full(7, 1.0)).times_s.to_numpy()
    assert np.allclose(np.diff(times)[1:], np.diff(unhurried)[1:])  # then at the plan's own pace
    assert speeds[0].max() * (times[1] / unhurried[1]) > 5.0  # unslowed, it would break the limit

"""Closed-loop execution: compare the tracked object with the path the chosen plan's rollout predicted.

While a push runs, the robot bridge reports the object's pose as its tracker sees it (with the plan
time it was seen at). `PushMonitor.observe` compares how far the object has moved and turned since
the first pose seen with how far the rollout predicted it would have by then; when the gap passes a
threshold (`MonitorThresholds`), it names why, and the push is stopped. Displacements, not poses,
are compared: the rollout started from the pose the planner was told, the robot pushes the object
where it truly stands (up to a centimetre away), and both are at rest before the hand arrives.

Only the push itself is watched (from the plan's push segment start to its end): before it nothing
should move, after it the hand backs off and stopping gains nothing.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from shared.contracts.messages import ExecutionState, ObjectPath, ObjectPose, Plan, PlanSegment
from shared.frames import pos_quat_to_matrix
from shared.world.push_outcome import pose_matrix


@dataclass(frozen=True)
class MonitorThresholds:
    """How far the tracked object may stray from the predicted path before the push is stopped.

    Chosen on the val objects under the `real` world: of 2 cm / 10° / 15°, 3 cm / 15° / 20°,
    4 cm / 25° / 30° and 6 cm / 35° / 40°, the third succeeded most, and above corrective pushes alone;
    tighter ones stop pushes that would have ended well (docs/evaluation.md §Tuned settings)."""

    position_m: float = 0.04  # the displacement's gap
    rotation_deg: float = 25.0  # turned this much further than predicted (in magnitude, either way)
    tilt_deg: float = 30.0  # the object's up axis leaning (a topple starting), beyond what was predicted


@dataclass(frozen=True)
class _Moved:
    """How far an object moved from a reference pose: horizontal displacement, yaw turned, tilt."""

    displacement: np.ndarray  # [2] m, world
    yaw_deg: float
    tilt_deg: float

    @classmethod
    def between(cls, reference: np.ndarray, now: np.ndarray) -> _Moved:
        relative = reference[:3, :3].T @ now[:3, :3]
        yaw = math.degrees(math.atan2(relative[1, 0] - relative[0, 1], relative[0, 0] + relative[1, 1]))
        up = float(np.clip(reference[:3, 2] @ now[:3, 2], -1.0, 1.0))
        return cls(now[:2, 3] - reference[:2, 3], yaw, math.degrees(math.acos(up)))


class PushMonitor:
    """Watches one executed push against `predicted` (the chosen plan's rollout, plan times)."""

    def __init__(self, plan: Plan, predicted: ObjectPath, push_direction_xy: np.ndarray,
                 thresholds: MonitorThresholds = MonitorThresholds(), watch_turn: bool = True):
        times = plan.times_s.to_numpy()
        push = next((s for s in plan.segments if s.label == "push"), None)
        if push is None:
            raise ValueError("a monitored plan needs a push segment")
        self.window_s = (float(times[push.start]), float(times[push.stop - 1]))
        self.predicted = predicted
        self.direction = np.asarray(push_direction_xy, dtype=np.float64) / np.linalg.norm(push_direction_xy)
        self.thresholds = thresholds
        # False for an object whose turn about the vertical no camera sees (a standing can, a ball): the tracked
        # turn is the tracker's guess, no reason to stop.
        self.watch_turn = watch_turn
        self._reference: tuple[float, np.ndarray] | None = None  # the first pose seen: (plan time, T_world_O)
        self._last_pose: ObjectPose | None = None
        self.observed = 0  # poses compared during the push
        self.stop_reason: str | None = None
        self.stop_time_s: float | None = None  # the plan time of the pose that stopped the push

    def observe_state(self, state: ExecutionState) -> str | None:
        """`observe` for a state the robot bridge published: those with a new tracked pose and a plan time
        (a state repeats the tracker's latest pose until the next frame); a state whose tracker lost the object
        during the push stops it (`lost`)."""
        if state.object_pose is None and state.object_lost is not None and state.plan_time_s is not None:
            return self.lost(state.plan_time_s, state.object_lost)
        if state.object_pose is None or state.plan_time_s is None or state.object_pose == self._last_pose:
            return None
        self._last_pose = state.object_pose
        return self.observe(state.plan_time_s, state.object_pose)

    def observe(self, plan_time_s: float, pose: ObjectPose) -> str | None:
        """A tracked pose at `plan_time_s`: why the push must stop now, or None to go on."""
        if self.stop_reason is not None or plan_time_s > self.window_s[1]:
            return None
        T = pose_matrix(pose)
        if self._reference is None:
            self._reference = (plan_time_s, T)
            return None
        if plan_time_s < self.window_s[0]:
            return None
        self.observed += 1
        seen = _Moved.between(self._reference[1], T)
        expected = _Moved.between(self._predicted_at(self._reference[0]), self._predicted_at(plan_time_s))
        self.stop_reason = self._verdict(plan_time_s, seen, expected)
        if self.stop_reason is not None:
            self.stop_time_s = plan_time_s
        return self.stop_reason

    def lost(self, plan_time_s: float, why: str) -> str | None:
        """The tracker lost the object at `plan_time_s`: during the push, stop it (pushing on would push on a
        stale pose); before it the hand has not touched the object, after it stopping gains nothing."""
        if self.stop_reason is not None or not self.window_s[0] <= plan_time_s <= self.window_s[1]:
            return None
        self.stop_reason = f"{plan_time_s - self.window_s[0]:.1f} s into the push the tracker lost the object ({why})"
        self.stop_time_s = plan_time_s
        return self.stop_reason

    def _verdict(self, t: float, seen: _Moved, expected: _Moved) -> str | None:
        limits = self.thresholds
        gap = seen.displacement - expected.displacement
        gap_m = float(np.linalg.norm(gap))
        when = f"{t - self.window_s[0]:.1f} s into the push"
        if gap_m > limits.position_m:
            along = float(gap @ self.direction)
            side = float(self.direction[0] * gap[1] - self.direction[1] * gap[0])  # left of the push: +
            way = ("behind" if along < 0 else "ahead of") if abs(along) >= abs(side) else "beside"
            return (f"{when} the object was {gap_m * 100:.1f} cm {way} the predicted path "
                    f"(moved {np.linalg.norm(seen.displacement) * 100:.1f} cm, predicted "
                    f"{np.linalg.norm(expected.displacement) * 100:.1f} cm)")
        # Turning is judged by how far, not which way: an object that turns less than predicted, or a
        # little the other way, is no reason to stop; one that turns further than predicted heads for the
        # 45° a push cannot undo.
        if self.watch_turn and abs(seen.yaw_deg) - abs(expected.yaw_deg) > limits.rotation_deg:
            return (f"{when} the object had turned {seen.yaw_deg:+.0f}° against a predicted "
                    f"{expected.yaw_deg:+.0f}°")
        if seen.tilt_deg - expected.tilt_deg > limits.tilt_deg:
            return f"{when} the object leaned {seen.tilt_deg:.0f}° (predicted {expected.tilt_deg:.0f}°): it is toppling"
        return None

    def _predicted_at(self, t: float) -> np.ndarray:
        """The predicted object pose at plan time t (the nearest sample; held at the path's ends)."""
        times = self.predicted.times_s.to_numpy()
        k = int(np.clip(np.searchsorted(times, t), 0, len(times) - 1))
        if k > 0 and abs(times[k - 1] - t) < abs(times[k] - t):
            k -= 1
        T: np.ndarray = pos_quat_to_matrix(self.predicted.positions.to_numpy()[k],
                                           self.predicted.quaternions_xyzw.to_numpy()[k])
        return T


BACK_OUT_LEAD_S = 0.1  # the way back's first waypoint is at least this far back along the plan: the robot,
# stopped a little behind its command, gets that long to reach it (never a jump the speed check refuses)


LIMIT_MARGIN_RAD = 1e-6  # the way back starts this far inside a limit that a joint was pushed past
# The way back's first step (from where the robot stopped to the plan's waypoint) moves no joint faster than this
# share of its velocity limit: a compliant finger the object pushed a radian off its command returns slowly
# instead of being refused by the bridge's speed check.
BACK_OUT_VELOCITY_SHARE = 0.5


def backed_out(plan: Plan, stop_time_s: float, q_now: np.ndarray, lower: np.ndarray, upper: np.ndarray,
               velocity: np.ndarray | None = None) -> Plan:
    """The way back along `plan` for a robot stopped at `q_now` about `stop_time_s` into it: the waypoints
    before that time in reverse, with the same timing, ending where the plan started. It retraces a path
    planned free of collisions, leaving the object behind (the push only moved it further on).

    A finger pressed against the object may stand past its joint limit (`lower`, `upper`: the plan's
    joints); the way back starts at the limit, where its motor holds it (the bridge checks a start so). With the
    joints' `velocity` limits, the first step takes long enough to move none faster than BACK_OUT_VELOCITY_SHARE of
    its limit (the rest follows at the plan's own pace)."""
    times, positions = plan.times_s.to_numpy(), plan.positions.to_numpy()
    q_now = np.clip(np.asarray(q_now, dtype=np.float64), lower + LIMIT_MARGIN_RAD, upper - LIMIT_MARGIN_RAD)
    k = int(np.searchsorted(times, stop_time_s - BACK_OUT_LEAD_S, side="right"))  # waypoints at or before
    if k == 0:
        path, back_times = positions[:1], np.array([BACK_OUT_LEAD_S])
    else:  # at the plan's own pace: waypoint j is reached as long after the stop as it came before it
        path, back_times = positions[:k][::-1], stop_time_s - times[:k][::-1]
    path = np.concatenate([np.asarray(q_now, dtype=np.float64)[None], path])
    back_times = np.concatenate([[0.0], back_times])
    if velocity is not None:
        slowest = float(np.max(np.abs(path[1] - path[0]) / (BACK_OUT_VELOCITY_SHARE * np.asarray(velocity))))
        back_times[1:] += max(0.0, slowest - back_times[1])
    return Plan(arm=plan.arm, hand=plan.hand, joint_names=list(plan.joint_names), positions=path, times_s=back_times,
                segments=[PlanSegment(label="retreat", start=0, stop=len(path))])

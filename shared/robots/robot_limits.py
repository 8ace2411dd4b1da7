"""Safety limits every robot backend enforces before anything moves (simulated today, hardware too).

A plan is refused — never clipped — when any waypoint breaks
- a joint position limit (URDF lower/upper, arm and hand);
- a joint velocity limit: finite differences of consecutive waypoints over `times_s`, against the
  URDF velocity limit × `velocity_scale` (hardware may run below the datasheet);
- the workspace box: the flange and the hand base must stay inside an axis-aligned box in the world
  (keeps a wrong frame or a runaway plan away from people and the table edge); `check_plan`
  checks it on the path densified so that no segment crosses a face unseen.
Effort limits are the motor torque caps a backend applies (`effort`); `check_efforts` checks
measured torques against them.

Every violation raises `LimitViolation`, whose message names the limit, the joint (or point), the
waypoint time and the offending value, e.g.
"joint velocity limit: panda_joint4 at t=1.240 s moves 3.100 rad/s > 2.175 rad/s".
The robot bridge reads each device's limits from here (`JointLimits`) and narrows them where the real
device is stricter (shared/execution/limits.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from shared.contracts.messages import Plan
from shared.robots.arms import ArmModel, load_arm, mount
from shared.robots.hands import HandModel, load_hand

# Tolerances for floating-point round trips of plan values (limits are checked, not re-derived).
POSITION_EPS_RAD = 1e-6
VELOCITY_EPS = 1e-6
WORKSPACE_STEP_RAD = 0.05  # densification of the path for the workspace check


class LimitViolation(ValueError):
    """A plan or a measurement outside a safety limit; `limit` is the kind, `joint` the name, `time_s` when."""

    def __init__(self, limit: str, joint: str, time_s: float, detail: str):
        super().__init__(f"{limit} limit: {joint} at t={time_s:.3f} s {detail}")
        self.limit = limit
        self.joint = joint
        self.time_s = time_s


@dataclass(frozen=True)
class WorkspaceBox:
    """Axis-aligned box in the world frame (metres)."""

    lower: tuple[float, float, float]
    upper: tuple[float, float, float]

    def contains(self, points: np.ndarray) -> np.ndarray | np.bool_:
        """Per point [..., 3]: inside the box (a numpy bool for a single point)."""
        points = np.asarray(points)
        return ((points >= np.asarray(self.lower)) & (points <= np.asarray(self.upper))).all(axis=-1)


# In front of and beside a table-mounted arm at the origin, above the table top (z = 0): the
# hand base of a push stands a few mm above the table, so the floor of the box is just below it.
DEFAULT_WORKSPACE = WorkspaceBox(lower=(-0.4, -0.85, -0.005), upper=(1.0, 0.85, 1.3))


@dataclass(frozen=True)
class JointLimits:
    """The joint limits in one URDF, an arm's or a hand's (its joint order): positions (rad), velocities
    (rad/s), efforts (N·m)."""

    joint_names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray

    @classmethod
    def of_arm(cls, arm: ArmModel | str) -> JointLimits:
        arm = load_arm(arm) if isinstance(arm, str) else arm
        return cls(tuple(arm.joint_names), _as_np(arm.joint_lower), _as_np(arm.joint_upper),
                   _as_np(arm.velocity_limits), _as_np(arm.effort_limits))

    @classmethod
    def of_hand(cls, hand: HandModel | str) -> JointLimits:
        hand = load_hand(hand) if isinstance(hand, str) else hand
        joints = [hand.robot.joint(name) for name in hand.joint_names]
        return cls(tuple(hand.joint_names), _as_np(hand.joint_lower), _as_np(hand.joint_upper),
                   np.array([j.velocity for j in joints], dtype=np.float64),
                   np.array([j.effort for j in joints], dtype=np.float64))


def _as_np(t: torch.Tensor) -> np.ndarray:
    return t.double().numpy()


@dataclass(frozen=True)
class RobotLimits:
    """Joint limits of an arm + hand (joint_names order: arm then hand) and the workspace box."""

    joint_names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    workspace: WorkspaceBox | None
    arm: ArmModel
    T_flange_hand: np.ndarray
    T_world_base: np.ndarray

    @classmethod
    def for_robot(
        cls,
        arm: ArmModel | str,
        hand: HandModel | str,
        *,
        workspace: WorkspaceBox | None = DEFAULT_WORKSPACE,
        velocity_scale: float = 1.0,
        T_world_base: np.ndarray | None = None,
    ) -> RobotLimits:
        """Limits from the URDFs of `arm` and `hand`; velocities scaled by `velocity_scale` (0, 1]."""
        if not 0.0 < velocity_scale <= 1.0:
            raise ValueError(f"velocity_scale must be in (0, 1], got {velocity_scale}")
        arm = load_arm(arm) if isinstance(arm, str) else arm
        hand = load_hand(hand) if isinstance(hand, str) else hand
        arm_joints, hand_joints = JointLimits.of_arm(arm), JointLimits.of_hand(hand)
        return cls(
            joint_names=(*arm_joints.joint_names, *hand_joints.joint_names),
            lower=np.concatenate([arm_joints.lower, hand_joints.lower]),
            upper=np.concatenate([arm_joints.upper, hand_joints.upper]),
            velocity=velocity_scale * np.concatenate([arm_joints.velocity, hand_joints.velocity]),
            effort=np.concatenate([arm_joints.effort, hand_joints.effort]),
            workspace=workspace,
            arm=arm,
            T_flange_hand=mount(arm, hand),
            T_world_base=np.eye(4) if T_world_base is None else np.asarray(T_world_base, dtype=np.float64),
        )

    # ------------------------------------------------------------------------------------ checks

    def check_plan(self, plan: Plan) -> None:
        """Raise LimitViolation for the earliest broken limit of `plan` (joints, velocities, workspace)."""
        positions = self.reorder(plan)
        times = plan.times_s.to_numpy().astype(np.float64)
        self.check_positions(positions, times)
        self.check_velocities(positions, times)
        if self.workspace is not None:
            self.check_workspace(*densify(positions, times, WORKSPACE_STEP_RAD))

    def reorder(self, plan: Plan) -> np.ndarray:
        """The plan's positions [T, n] in this robot's joint order; every joint must be present once."""
        names = list(plan.joint_names)
        missing = [n for n in self.joint_names if n not in names]
        extra = [n for n in names if n not in self.joint_names]
        if missing or extra:
            raise LimitViolation("joint set", ", ".join(missing + extra), 0.0,
                                 f"does not match the robot (missing {missing}, unknown {extra})")
        order = [names.index(n) for n in self.joint_names]
        return plan.positions.to_numpy().astype(np.float64)[:, order]

    def check_positions(self, positions: np.ndarray, times: np.ndarray) -> None:
        below = positions < self.lower - POSITION_EPS_RAD
        above = positions > self.upper + POSITION_EPS_RAD
        if below.any() or above.any():
            step, joint = _first(below | above)
            bound, side = (self.lower[joint], "below") if below[step, joint] else (self.upper[joint], "above")
            raise LimitViolation("joint position", self.joint_names[joint], times[step],
                                 f"is {positions[step, joint]:.4f} rad, {side} its limit {bound:.4f} rad")

    def check_velocities(self, positions: np.ndarray, times: np.ndarray) -> None:
        if len(times) < 2:
            return
        speed = np.abs(np.diff(positions, axis=0)) / np.diff(times)[:, None]
        too_fast = speed > self.velocity * (1.0 + VELOCITY_EPS)
        if too_fast.any():
            step, joint = _first(too_fast)
            raise LimitViolation("joint velocity", self.joint_names[joint], times[step + 1],
                                 f"moves {speed[step, joint]:.3f} rad/s > {self.velocity[joint]:.3f} rad/s")

    def check_workspace(self, positions: np.ndarray, times: np.ndarray) -> None:
        """Flange and hand base inside the box at every given waypoint (densify the path first).
        Nothing to check without a box (`workspace` None)."""
        workspace = self.workspace
        if workspace is None:
            return
        points = self.tool_points(positions[:, : self.arm.dof])
        outside = ~np.asarray(workspace.contains(points))  # [T, 2]
        if outside.any():
            step, which = _first(outside)
            name = (f"flange ({self.arm.flange_link})", "hand base")[which]
            raise LimitViolation("workspace box", name, times[step],
                                 f"is at {np.round(points[step, which], 3).tolist()} m, outside the box "
                                 f"{list(workspace.lower)} .. {list(workspace.upper)}")

    def tool_points(self, arm_positions: np.ndarray) -> np.ndarray:
        """World positions [T, 2, 3] of the flange and the hand base for arm joints [T, dof]."""
        with torch.no_grad():
            flange = self.arm.flange_pose(torch.as_tensor(arm_positions, dtype=torch.float32)).double().numpy()
        flange_world = self.T_world_base @ flange
        hand_world = flange_world @ self.T_flange_hand
        return np.stack([flange_world[:, :3, 3], hand_world[:, :3, 3]], axis=1)

    def check_efforts(self, torques: np.ndarray, time_s: float) -> None:
        """Measured joint torques [n] (joint_names order) against the effort limits."""
        torques = np.asarray(torques, dtype=np.float64)
        over = np.abs(torques) > self.effort * (1.0 + VELOCITY_EPS)
        if over.any():
            joint = int(np.argmax(over))
            raise LimitViolation("joint effort", self.joint_names[joint], time_s,
                                 f"exerts {abs(torques[joint]):.2f} N·m > {self.effort[joint]:.2f} N·m")


def densify(positions: np.ndarray, times: np.ndarray, max_step_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Insert waypoints (and their times) so no joint moves more than `max_step_rad` between two."""
    pieces, stamps = [positions[:1]], [times[:1]]
    for i in range(len(positions) - 1):
        steps = max(1, int(np.ceil(np.max(np.abs(positions[i + 1] - positions[i])) / max_step_rad)))
        alphas = np.linspace(0.0, 1.0, steps + 1)[1:]
        pieces.append(positions[i] + alphas[:, None] * (positions[i + 1] - positions[i]))
        stamps.append(times[i] + alphas * (times[i + 1] - times[i]))
    return np.concatenate(pieces), np.concatenate(stamps)


def _first(mask: np.ndarray) -> tuple[int, int]:
    """(row, column) of the first True in row-major order (the earliest waypoint)."""
    row_column: tuple[int, int] = divmod(int(np.argmax(mask.reshape(-1))), mask.shape[1])
    return row_column

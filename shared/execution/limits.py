"""The limits a command is checked against before anything moves, and the refusal that names the broken one.

- `DeviceLimits`: one device's per-joint limits, read from its URDF (`shared.robots.robot_limits.JointLimits`);
  a device's config (`robots/<name>/config.py`) types only what the URDF lacks or the real device
  differs on (the FR3's ranges and speeds against the Panda model's, a hand's current cap in mA),
  each with its source.
- `plan_limits`: the plan-level `RobotLimits` of an arm + hand (joint positions, velocities, the
  workspace box for the flange and the hand base), narrowed by each device's limits where the device
  is stricter.
- `check_plan`: every waypoint inside the position limits, every segment's speed at the timing the
  joints will move inside the velocity limits, the densified tool path inside the workspace box.

A violation raises `SafetyRefusal` (nothing has moved); no module here knows of the bus.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from shared.contracts.messages import Plan
from shared.execution.robot import RobotError
from shared.robots.robot_limits import (
    DEFAULT_WORKSPACE,
    WORKSPACE_STEP_RAD,
    JointLimits,
    LimitViolation,
    RobotLimits,
    WorkspaceBox,
    densify,
)


class SafetyRefusal(RobotError):
    """A command was refused by a safety check before anything moved; `check` names which one."""

    def __init__(self, check: str, message: str):
        super().__init__(f"{check}: {message}")
        self.check = check


@dataclass(frozen=True)
class DeviceLimits:
    """Per-joint limits of one device. `effort` is in `effort_unit` (what the device can cap: Nm or mA)."""

    device: str
    joint_names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    effort_unit: str = "Nm"

    def __post_init__(self) -> None:
        n = len(self.joint_names)
        for name in ("lower", "upper", "velocity", "effort"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != (n,):
                raise ValueError(f"{self.device}: {name} limits need {n} values, got shape {value.shape}")
            object.__setattr__(self, name, value)
        object.__setattr__(self, "joint_names", tuple(self.joint_names))
        if np.any(self.lower >= self.upper) or np.any(self.velocity <= 0) or np.any(self.effort <= 0):
            raise ValueError(f"{self.device}: limits must satisfy lower < upper and velocity, effort > 0")

    @classmethod
    def from_urdf(cls, device: str, urdf: JointLimits, *, lower: Sequence[float] | None = None,
                  upper: Sequence[float] | None = None, velocity: Sequence[float] | None = None,
                  effort: Sequence[float] | None = None, effort_unit: str = "Nm") -> DeviceLimits:
        """The URDF's limits, each kind replaced by the real device's numbers where given."""
        return cls(device, urdf.joint_names,
                   lower=urdf.lower if lower is None else np.asarray(lower, dtype=np.float64),
                   upper=urdf.upper if upper is None else np.asarray(upper, dtype=np.float64),
                   velocity=urdf.velocity if velocity is None else np.asarray(velocity, dtype=np.float64),
                   effort=urdf.effort if effort is None else np.asarray(effort, dtype=np.float64),
                   effort_unit=effort_unit)

    def check_effort_cap(self, cap: np.ndarray | None) -> None:
        """SafetyRefusal if the device is configured to allow more effort than its limit."""
        if cap is None:
            return
        cap = np.asarray(cap, dtype=np.float64)
        if (cap > self.effort).any():
            joint = int(np.argmax(cap - self.effort))
            raise SafetyRefusal("effort_limits", f"{self.device} joint {self.joint_names[joint]} is configured for "
                                f"{cap[joint]:g} {self.effort_unit}, above its limit {self.effort[joint]:g} {self.effort_unit}")

    def check_measured_effort(self, efforts: np.ndarray | None) -> str | None:
        """A message naming the first joint whose measured |effort| exceeds its limit, else None."""
        if efforts is None:
            return None
        over = np.abs(np.asarray(efforts, dtype=np.float64)) > self.effort
        if not over.any():
            return None
        joint = int(np.argmax(over))
        return (f"{self.device} joint {self.joint_names[joint]} effort {efforts[joint]:g} {self.effort_unit} "
                f"exceeds {self.effort[joint]:g}")


def plan_limits(arm: str, hand: str, devices: Sequence[DeviceLimits], workspace: WorkspaceBox | None = DEFAULT_WORKSPACE,
                T_world_base: np.ndarray | None = None) -> RobotLimits:
    """Plan-level limits of an arm + hand: `RobotLimits` from the URDFs (joint positions, velocities, the
    workspace box for the flange and the hand base) narrowed by each device's own limits where the real
    device is stricter (e.g. the FR3's joints 4 and 6 against the Panda model)."""
    limits = RobotLimits.for_robot(arm, hand, workspace=workspace, T_world_base=T_world_base)
    lower, upper, velocity = limits.lower.copy(), limits.upper.copy(), limits.velocity.copy()
    index = {name: i for i, name in enumerate(limits.joint_names)}
    for device in devices:
        for k, name in enumerate(device.joint_names):
            if name not in index:
                raise ValueError(f"{device.device} joint {name!r} is not a joint of {arm} + {hand}")
            i = index[name]
            lower[i] = max(lower[i], device.lower[k])
            upper[i] = min(upper[i], device.upper[k])
            velocity[i] = min(velocity[i], device.velocity[k])
    return replace(limits, lower=lower, upper=upper, velocity=velocity)


def check_plan(limits: RobotLimits, plan: Plan, time_scale: float = 1.0) -> None:
    """SafetyRefusal unless every waypoint, every segment's speed with the plan `time_scale` times faster
    (the timing the joints will move at) and the densified tool path are inside `limits`."""
    try:
        positions = limits.reorder(plan)
        times = plan.times_s.to_numpy().astype(np.float64) / time_scale
        limits.check_positions(positions, times)
        limits.check_velocities(positions, times)
        if limits.workspace is not None:
            limits.check_workspace(*densify(positions, times, WORKSPACE_STEP_RAD))
    except LimitViolation as exc:
        raise SafetyRefusal(exc.limit, str(exc)) from None

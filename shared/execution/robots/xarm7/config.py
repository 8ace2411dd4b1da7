"""The UFactory xArm7 (arm `xarm7`): its config and its device limits.

Every limit is its URDF's (xarm_description's xarm7.urdf, shared/robots/arms.py): joint ranges, speeds and
efforts in Nm, the unit the SDK reports measured torques in.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

from shared.execution.limits import DeviceLimits
from shared.robots.robot_limits import JointLimits


@dataclass(frozen=True)
class XArm7Config:
    """The xArm7 controller at `ip`, streaming servo targets at `command_rate_hz`."""

    ip: str
    command_rate_hz: float = 100.0
    settle_tolerance_rad: float = 0.01
    settle_timeout_s: float = 2.0


@functools.cache
def limits() -> DeviceLimits:
    return DeviceLimits.from_urdf("xarm7", JointLimits.of_arm("xarm7"))

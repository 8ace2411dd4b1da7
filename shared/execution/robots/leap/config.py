"""The LEAP hand (hand `leap`): its config and its device limits.

Joint ranges and speeds are its URDF's (LEAP_Hand_Sim robot.urdf, shared/robots/hands). The effort limit is
the Dynamixel goal-current cap in mA, which the URDF (torques) does not give: current-based position
mode never exceeds it, and 550 mA is the LEAP authors' setting for the full hand.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

from shared.execution.limits import DeviceLimits
from shared.robots.robot_limits import JointLimits

CURRENT_LIMIT_MA = 550.0


@dataclass(frozen=True)
class LeapConfig:
    """The LEAP hand on a serial port (e.g. /dev/ttyUSB0), motor ids `motor_ids` in joint order."""

    port: str
    baudrate: int = 4_000_000
    motor_ids: tuple[int, ...] = tuple(range(16))
    current_limit_ma: float = CURRENT_LIMIT_MA  # the effort cap the motors are configured with
    command_rate_hz: float = 100.0
    settle_tolerance_rad: float = 0.02
    settle_timeout_s: float = 1.0
    retries: int = 3  # a lost status packet is retried, as on a real USB-serial link


@functools.cache
def limits() -> DeviceLimits:
    return DeviceLimits.from_urdf("leap", JointLimits.of_hand("leap"), effort=[CURRENT_LIMIT_MA] * 16, effort_unit="mA")

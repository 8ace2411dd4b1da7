"""The Allegro hand V5 (hand `allegro`): its config and its device limits.

Joint ranges and speeds are its URDF's (example-robot-data's allegro_right_hand.urdf, shared/robots/hands).
The effort limit is the V5 driver's torque-command clamp, +-240 in its CAN units (~mA;
AllegroHandDrv.cpp), which is what the hand reports and we monitor; the URDF gives torques instead.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

from shared.execution.limits import DeviceLimits
from shared.robots.robot_limits import JointLimits

CURRENT_CLAMP = 240.0


@dataclass(frozen=True)
class AllegroConfig:
    """The Allegro hand V5 on a CAN interface (e.g. interface='socketcan', channel='can0', 1 Mbit/s)."""

    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int | None = 1_000_000
    report_period_ms: int = 5
    connect_timeout_s: float = 1.0
    stale_after_s: float = 0.2
    command_rate_hz: float = 100.0
    settle_tolerance_rad: float = 0.02
    settle_timeout_s: float = 1.0
    h_inf_firmware: bool = False  # position targets on the SET_TORQUE ids (protocol.py)


@functools.cache
def limits() -> DeviceLimits:
    return DeviceLimits.from_urdf("allegro", JointLimits.of_hand("allegro"), effort=[CURRENT_CLAMP] * 16,
                                  effort_unit="mA")

"""The Franka Research 3 behind the arm name `panda`: its config and its device limits.

Plans name the arm's joints as the Panda model does (shared/robots/arms.py), which has the FR3's kinematic
chain; the real FR3's joint ranges and speeds differ from that model's URDF (joints 4 and 6 most), so
those are typed here from the FR3's own description. Efforts (Nm) are the URDF's.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

from shared.execution.limits import DeviceLimits
from shared.robots.robot_limits import JointLimits

# External-torque reflex thresholds (Nm): libfranka's default-behaviour values (20, 20, 18, 18, 16, 14, 12)
# capped at each joint's rated torque (12 Nm for joints 5-7), so the cap never exceeds the effort limit.
DEFAULT_COLLISION_TORQUE_NM: tuple[float, ...] = (20.0, 20.0, 18.0, 18.0, 12.0, 12.0, 12.0)

# Franka Research 3 joint limits (franka_description's fr3 joint limits; identical to franky-sim's assets/fr3.urdf).
FR3_LOWER = (-2.9007, -1.8361, -2.9007, -3.0770, -2.8763, 0.4398, -3.0508)
FR3_UPPER = (2.9007, 1.8361, 2.9007, -0.1169, 2.8763, 4.6216, 3.0508)
FR3_VELOCITY = (2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26)


@dataclass(frozen=True)
class PandaConfig:
    """The FR3 at `host` (its FCI address, or 127.0.0.1 for franky-sim)."""

    host: str
    relative_dynamics_factor: float = 0.2
    collision_torque_nm: tuple[float, ...] = DEFAULT_COLLISION_TORQUE_NM  # the effort cap (reflex threshold)
    realtime: bool = True  # False only for simulators / non-RT kernels (libfranka's RealtimeConfig.Ignore)
    settle_tolerance_rad: float = 0.01
    poll_period_s: float = 0.01


@functools.cache
def limits() -> DeviceLimits:
    return DeviceLimits.from_urdf("panda", JointLimits.of_arm("panda"), lower=FR3_LOWER, upper=FR3_UPPER,
                                  velocity=FR3_VELOCITY)

"""The simulated robot's config: which arm + hand, where its base stands, the physics it runs, its tracker.

Its limits are its URDFs' (`limits`): a simulation has no datasheet to be stricter than them.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from shared.execution.limits import DeviceLimits
from shared.execution.robots import TRACKING_MODES, TrackingMode
from shared.execution.robots.sim.tracker import TrackerConfig
from shared.robots.robot_limits import JointLimits
from shared.world.perception.tracking import TrackingConfig
from shared.world.sim.params import REFERENCE_PARAMS, PhysicsParams


@dataclass(frozen=True)
class SimConfig:
    arm: str
    hand: str
    T_world_base: np.ndarray | None = None  # the arm's base in the world (None: at the origin)
    params: PhysicsParams = REFERENCE_PARAMS  # the physics of a world reset without its own
    state_rate_hz: float = 50.0  # states published per second of robot time
    # How the robot sees the object: "image" (registered in rendered depth frames, camera_tracker.py) or
    # "truth" (the true pose, late and noisy: tracker.py's TrackerConfig).
    tracking: TrackingMode = "image"
    image_tracking: TrackingConfig = TrackingConfig()
    tracker: TrackerConfig = TrackerConfig()

    def __post_init__(self) -> None:
        if self.state_rate_hz <= 0:
            raise ValueError(f"state_rate_hz must be positive, got {self.state_rate_hz}")
        if self.tracking not in TRACKING_MODES:
            raise ValueError(f"tracking must be one of {', '.join(TRACKING_MODES)}, got {self.tracking!r}")


@functools.cache
def limits(arm: str, hand: str) -> DeviceLimits:
    arm_joints, hand_joints = JointLimits.of_arm(arm), JointLimits.of_hand(hand)
    merged = JointLimits(
        (*arm_joints.joint_names, *hand_joints.joint_names),
        *(np.concatenate([getattr(arm_joints, k), getattr(hand_joints, k)]) for k in ("lower", "upper", "velocity", "effort")))
    return DeviceLimits.from_urdf(f"{arm}+{hand}", merged)

"""The MuJoCo robot's config: which arm + hand, where its base stands, its contact model and controller.

Its limits are its URDFs' (the same `sim.config.limits` as the PyBullet robot: one arm + hand, one set of
limits). The contact settings are MuJoCo's own, chosen by a measurement (`bench/mujoco_contact.py`,
`bench/results/mujoco_contact.json`, docs/architecture.md "A second world"), not matched to PyBullet's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from shared.execution.robots import TrackingMode
from shared.execution.robots.sim.tracker import TrackerConfig
from shared.world.perception.tracking import TrackingConfig
from shared.world.sim.world import MujocoDraw


@dataclass(frozen=True)
class ContactConfig:
    """MuJoCo's soft-contact model and solver (see the bench for why these values)."""

    time_step_s: float = 0.002
    cone: Literal["pyramidal", "elliptic"] = "elliptic"
    solver: Literal["Newton", "CG", "PGS"] = "Newton"
    iterations: int = 50
    # solref (time constant s, damping ratio) and solimp (dmin, dmax, width m): how soft a contact is.
    solref: tuple[float, float] = (0.02, 1.0)
    solimp: tuple[float, float, float] = (0.9, 0.95, 0.001)
    noslip_iterations: int = 0
    impratio: float = 1.0  # elliptic cones: ratio of frictional to normal impedance

    def __post_init__(self) -> None:
        if not 0 < self.time_step_s <= 0.01:
            raise ValueError(f"time_step_s must be in (0, 0.01], got {self.time_step_s}")
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.solref[0] < 2 * self.time_step_s:
            raise ValueError(f"solref time constant {self.solref[0]} s is below twice the time step: unstable")


@dataclass(frozen=True)
class MaterialConfig:
    """Friction of the materials in contact. Nominal values of the materials (wood-like table,
    rubber-tipped fingers, a rigid object): they are the world's, drawn per trial at world level `mujoco`
    (`MujocoConfig.drawn`), not engine settings.

    MuJoCo takes a contact's coefficients from the geom of higher priority (the larger of the two at equal
    priority): the table and the robot outrank the object, so object-table contacts take `table_friction`
    and hand-object contacts `hand_friction` (times the finger's scale); `object_friction` acts against
    obstacles only. `condim` 3 is sliding friction alone (what the contact bench measured); 6 adds the
    torsional and rolling friction (a drawn world's)."""

    table_friction: float = 0.5
    object_friction: float = 0.5
    hand_friction: float = 0.8
    torsional_friction: float = 0.005
    rolling_friction: float = 0.0001
    finger_friction_scales: tuple[float, ...] = ()  # one per finger (index, middle, ring, thumb); () all 1
    condim: Literal[3, 4, 6] = 3

    def __post_init__(self) -> None:
        values = {"table_friction": self.table_friction, "object_friction": self.object_friction,
                  "hand_friction": self.hand_friction, "torsional_friction": self.torsional_friction,
                  "rolling_friction": self.rolling_friction,
                  **{f"finger_friction_scales[{k}]": v for k, v in enumerate(self.finger_friction_scales)}}
        for name, value in values.items():
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a finite coefficient >= 0, got {value}")
        if self.condim not in (3, 4, 6):
            raise ValueError(f"condim must be 3, 4 or 6, got {self.condim}")


@dataclass(frozen=True)
class ControlConfig:
    """Joint position servos: force = kp (q_ref - q) + kv (qd_ref - qd), capped at the URDF effort, with
    gravity compensation (as the Panda's and xArm's controllers and the hands' servos hold their links)."""

    arm_kp: float = 2000.0  # Nm/rad
    arm_kv: float = 150.0  # Nm s/rad
    arm_armature: float = 0.1  # kg m^2, reflected rotor inertia (Panda's joint motors ~0.1)
    hand_kp: float = 3.0
    hand_kv: float = 0.1
    hand_armature: float = 0.001
    hand_damping: float = 0.01  # Nm s/rad, passive (the PyBullet robot's nominal hand joint damping)
    settle_s: float = 0.3  # held at the final waypoint after a trajectory (as the PyBullet robot settles)
    command_latency_s: float = 0.0  # how late each command reaches the servos (a real arm's command path)

    def __post_init__(self) -> None:
        gains = {"arm_kp": self.arm_kp, "arm_kv": self.arm_kv, "hand_kp": self.hand_kp, "hand_kv": self.hand_kv}
        for name, value in gains.items():
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {value}")
        if not (math.isfinite(self.hand_damping) and self.hand_damping >= 0.0):
            raise ValueError(f"hand_damping must be finite and >= 0, got {self.hand_damping}")
        if not (math.isfinite(self.command_latency_s) and 0.0 <= self.command_latency_s < self.settle_s):
            raise ValueError(f"command_latency_s must be in [0, settle_s = {self.settle_s}), got {self.command_latency_s}")


@dataclass(frozen=True)
class MujocoConfig:
    arm: str
    hand: str
    T_world_base: np.ndarray | None = None  # the arm's base in the world (None: at the origin)
    contact: ContactConfig = ContactConfig()
    materials: MaterialConfig = MaterialConfig()
    control: ControlConfig = ControlConfig()
    state_rate_hz: float = 50.0  # states published per second of robot time
    # How the robot sees the object: "image" (registered in depth frames MuJoCo renders, camera_tracker.py) or
    # "truth" (the true pose, late and noisy: TrackerConfig).
    tracking: TrackingMode = "image"
    image_tracking: TrackingConfig = TrackingConfig()
    tracker: TrackerConfig = TrackerConfig()

    def __post_init__(self) -> None:
        if self.state_rate_hz <= 0:
            raise ValueError(f"state_rate_hz must be positive, got {self.state_rate_hz}")

    def drawn(self, draw: MujocoDraw) -> MujocoConfig:
        """This config in a drawn world (`shared.world.sim.world.MujocoDraw`): its materials the draw's
        coefficients with torsional and rolling friction acting (condim 6), its servos' gains scaled, its
        command latency the draw's. The object's mass and centre of mass are the placed object's."""
        materials = replace(self.materials, table_friction=draw.table_friction, object_friction=draw.table_friction,
                            hand_friction=draw.hand_friction, torsional_friction=draw.torsional_friction_m,
                            rolling_friction=draw.rolling_friction_m,
                            finger_friction_scales=tuple(draw.finger_friction_scales), condim=6)
        c = self.control
        control = replace(c, arm_kp=c.arm_kp * draw.arm_kp_scale, arm_kv=c.arm_kv * draw.arm_kv_scale,
                          hand_kp=c.hand_kp * draw.finger_stiffness_scale,
                          hand_kv=c.hand_kv * draw.finger_damping_scale,
                          hand_damping=c.hand_damping * draw.finger_damping_scale,
                          command_latency_s=draw.command_latency_s)
        return replace(self, materials=materials, control=control)

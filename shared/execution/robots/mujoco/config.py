"""The MuJoCo robot's config: which arm + hand, where its base stands, its contact model and controller.

Its limits are its URDFs' (the same `sim.config.limits` as the PyBullet robot: one arm + hand, one set of
limits). The contact settings are MuJoCo's own, chosen by a measurement (`bench/mujoco_contact.py`,
`bench/results/mujoco_contact.json`, docs/architecture.md "A second world"), not matched to PyBullet's.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from shared.execution.robots.sim.tracker import TrackerConfig


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
    """Sliding friction of the three materials in contact (MuJoCo combines a pair by the larger value).
    Nominal values of the materials (wood-like table, rubber-tipped fingers, a rigid object): they are
    the world's, drawn per trial by item 2's randomisation, not engine settings."""

    table_friction: float = 0.5
    object_friction: float = 0.5
    hand_friction: float = 0.8
    torsional_friction: float = 0.005
    rolling_friction: float = 0.0001


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


@dataclass(frozen=True)
class MujocoConfig:
    arm: str
    hand: str
    T_world_base: np.ndarray | None = None  # the arm's base in the world (None: at the origin)
    contact: ContactConfig = ContactConfig()
    materials: MaterialConfig = MaterialConfig()
    control: ControlConfig = ControlConfig()
    state_rate_hz: float = 50.0  # states published per second of robot time
    tracker: TrackerConfig = TrackerConfig()  # how the robot sees the object (until item 3's image tracker)

    def __post_init__(self) -> None:
        if self.state_rate_hz <= 0:
            raise ValueError(f"state_rate_hz must be positive, got {self.state_rate_hz}")

"""Physics parameters of every push simulation, each with the measurement that justified it.

PLACEHOLDER VALUES: being measured.
"""
from __future__ import annotations

from dataclasses import dataclass, replace


@dataclass(frozen=True)
class PhysicsParams:
    solver_iterations: int = 20
    time_step_s: float = 1.0 / 120.0
    push_speed_mps: float = 0.10
    settle_s: float = 0.25
    gravity_mps2: float = 9.81
    table_friction: float = 0.5
    object_friction: float = 1.0
    object_rolling_friction: float = 0.0
    hand_friction: float = 0.8
    hand_joint_damping: float = 0.01
    hand_joint_force_scale: float = 1.0
    hand_position_gain: float = 1.0
    base_constraint_force_n: float = 500.0
    constraint_erp: float = 0.8

    def with_solver(self, solver_iterations: int, time_step_s: float) -> "PhysicsParams":
        return replace(self, solver_iterations=solver_iterations, time_step_s=time_step_s)


REFERENCE_PARAMS = PhysicsParams().with_solver(50, 1.0 / 240.0)

"""The world a plan is executed in, drawn apart from what the planner knows.

The planner knows nominal physics (`PhysicsParams()`), the object's model and the pose it is told.
A real robot meets an object whose friction, mass and centre of mass differ from the model's,
standing a little away from where perception put it, and an arm whose controller tracks a little
differently. `sample_world(level, seed, ...)` draws one such execution world per trial:

- `exact`: the planner's world itself (the execution is the rollout's physics at the bridge's solver
  settings, the told pose is the true pose): the committed results before execution worlds existed;
- `real` (the evaluation's default): every quantity below drawn uniformly from its range.

| quantity | nominal | `real` range | what it rests on |
|---|---|---|---|
| object-table friction | 0.5 | ×U(0.6, 1.4): 0.30-0.70 | handbook static coefficients of wood, plastic, cardboard and ceramic on wood or laminate span ~0.2-0.6; the same ± range the first perturbation study used |
| hand-object friction | 0.8 | ×U(0.6, 1.4): 0.48-1.12 | rubber / silicone finger pads on plastic and painted surfaces ~0.5-1.2 |
| object mass | model (uniform density; the everyday procedural families: their designed mass) | ×U(0.7, 1.4) | a mass guessed from a shape: hollow objects are lighter, filled ones heavier |
| centre of mass | the model's centroid | offset up to 20% of the half extent along each horizontal axis, 10% vertically | an uneven fill (a mug's handle, contents settling) |
| rolling friction | 0 | U(0, 0.002) | PyBullet's rolling resistance; small enough that nothing rolls away by itself |
| arm position gain | 0.3 | ×U(0.7, 1.3) | a controller tuned on another payload tracks a few mrad differently |
| command latency | 0 | U(0, 0.02) s | FR3 via franky: 1 kHz loop, a few ms; xArm servo mode: 4-10 ms plus the network |
| told pose vs true pose | equal | ±1 cm in x and y, ±5° yaw | object pose from a tabletop camera or a fiducial: typical errors 0.5-1.5 cm, a few degrees |

Rollouts never see an execution world: it goes to the robot (the evaluation's simulated robot), the
planner gets the told pose. A planner that ranks for robustness (`PlannerOptions.physics_draws`) rolls
each plan out in worlds of its own, `rollout_worlds`: drawn from the same ranges (the planner's prior
about what it does not know) with seeds derived from the request's, never the execution's draw.

Perception (`cameras`): with 0 the system is told the object's mesh and a pose off by `pose_error`;
with 1-3 it receives instead what that many simulated depth cameras see (`shared.world.sim.camera`: a
noisy point cloud of the object standing at its true pose) and reconstructs the object from it, so
its shape and pose errors are perception's own and no pose error is drawn.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any, Literal

import numpy as np

from shared.frames import make_transform, yaw_rotation
from shared.world.sim.params import REFERENCE_PARAMS, PhysicsParams

WorldLevel = Literal["exact", "real"]
WORLD_LEVELS: tuple[WorldLevel, ...] = ("exact", "real")


@dataclass(frozen=True)
class Uniform:
    low: float
    high: float

    def draw(self, rng: np.random.Generator) -> float:
        return float(rng.uniform(self.low, self.high))


@dataclass(frozen=True)
class WorldRanges:
    """The `real` level's ranges (the module's table says what each rests on)."""

    table_friction_scale: Uniform = Uniform(0.6, 1.4)
    hand_friction_scale: Uniform = Uniform(0.6, 1.4)
    mass_scale: Uniform = Uniform(0.7, 1.4)
    com_offset_fraction_xy: float = 0.2  # of the object's half extent along x and y of its frame O
    com_offset_fraction_z: float = 0.1
    rolling_friction: Uniform = Uniform(0.0, 0.002)
    position_gain_scale: Uniform = Uniform(0.7, 1.3)
    command_latency_s: Uniform = Uniform(0.0, 0.02)
    pose_error_m: float = 0.01  # uniform in a ±1 cm square
    pose_error_deg: float = 5.0  # uniform yaw in ±5°


REAL_RANGES = WorldRanges()


@dataclass(frozen=True)
class PoseError:
    """Where the object truly is, relative to where the system is told it is: a shift in the table
    plane and a turn about the vertical through the told position."""

    dx_m: float = 0.0
    dy_m: float = 0.0
    dyaw_deg: float = 0.0

    def true_pose(self, T_world_O_told: np.ndarray) -> np.ndarray:
        """T_world_O of the object's true pose, given the told one."""
        told = np.asarray(T_world_O_told, dtype=np.float64)
        turn = make_transform(yaw_rotation(math.radians(self.dyaw_deg)), np.zeros(3))
        true: np.ndarray = turn @ make_transform(told[:3, :3], np.zeros(3))
        true[:3, 3] = told[:3, 3] + np.array([self.dx_m, self.dy_m, 0.0])
        return true


@dataclass(frozen=True)
class ExecutionWorld:
    """One drawn execution world: the physics the robot meets, the true object, the pose error."""

    level: WorldLevel
    seed: int
    physics: PhysicsParams
    mass_scale: float = 1.0
    com_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # in the object's frame O
    pose_error: PoseError = PoseError()
    cameras: int = 0  # 0: the system is told the mesh (and a pose off by pose_error); 1-3: a camera cloud

    def record(self) -> dict[str, Any]:
        """What a result record keeps of the world (the drawn values, not the solver settings)."""
        p = self.physics
        return {"level": self.level, "seed": self.seed, "table_friction": round(p.table_friction, 4),
                "hand_friction": round(p.hand_friction, 4), "rolling_friction": round(p.object_rolling_friction, 5),
                "mass_scale": round(self.mass_scale, 4), "com_offset_m": [round(v, 4) for v in self.com_offset_m],
                "position_gain": round(p.arm_position_gain, 4), "latency_s": round(p.arm_command_latency_s, 4),
                "pose_error": {k: round(v, 4) for k, v in asdict(self.pose_error).items()}, "cameras": self.cameras}


def half_extents(vertices_o: np.ndarray) -> np.ndarray:
    """An object's half extents along the axes of its frame O, from its mesh vertices in O (what a
    centre-of-mass offset is drawn in)."""
    vertices = np.asarray(vertices_o, dtype=np.float64)
    extents: np.ndarray = (vertices.max(axis=0) - vertices.min(axis=0)) / 2.0
    return extents


ROLLOUT_SEED_SALT = 0x5EED_D2A3  # keeps a planner's own draws apart from every evaluation's world seeds


def rollout_worlds(request_seed: int, count: int, half_extents_m: np.ndarray,
                   base: PhysicsParams, ranges: WorldRanges = REAL_RANGES) -> list[ExecutionWorld]:
    """`count` worlds the planner rolls its plans out in to rank them for robustness: `real` draws
    around its nominal physics `base`, the same draws for every plan of a request (common random
    numbers: plans are compared in the same worlds), seeded from the request's seed."""
    worlds = []
    for k in range(count):
        seed = int(np.random.SeedSequence([request_seed, ROLLOUT_SEED_SALT, k]).generate_state(1, np.uint64)[0] >> 1)
        worlds.append(sample_world("real", seed, half_extents_m, base=base, ranges=ranges))
    return worlds


def sample_world(level: WorldLevel, seed: int, half_extents_m: np.ndarray,
                 base: PhysicsParams = REFERENCE_PARAMS, ranges: WorldRanges = REAL_RANGES,
                 cameras: int = 0) -> ExecutionWorld:
    """The execution world of one trial. `half_extents_m`: the object's half extents along its frame
    O's axes (for the centre-of-mass offset); `base`: the solver settings and nominal physics;
    `cameras`: 0 (the mesh is told) or how many depth cameras the system sees the object with."""
    if level not in WORLD_LEVELS:
        raise ValueError(f"unknown world level {level!r}; known: {', '.join(WORLD_LEVELS)}")
    if cameras not in (0, 1, 2, 3):
        raise ValueError(f"cameras must be 0 (the mesh is told) or 1-3, got {cameras}")
    if level == "exact":
        return ExecutionWorld("exact", seed, base, cameras=cameras)
    rng = np.random.default_rng(seed)
    physics = replace(base, table_friction=base.table_friction * ranges.table_friction_scale.draw(rng),
                      hand_friction=base.hand_friction * ranges.hand_friction_scale.draw(rng),
                      object_rolling_friction=ranges.rolling_friction.draw(rng),
                      arm_position_gain=base.arm_position_gain * ranges.position_gain_scale.draw(rng),
                      arm_command_latency_s=ranges.command_latency_s.draw(rng))
    fractions = np.array([ranges.com_offset_fraction_xy] * 2 + [ranges.com_offset_fraction_z])
    com = rng.uniform(-1.0, 1.0, 3) * fractions * np.asarray(half_extents_m, dtype=np.float64)
    dx, dy = (float(v) for v in rng.uniform(-ranges.pose_error_m, ranges.pose_error_m, 2))
    error = PoseError(dx, dy, float(rng.uniform(-ranges.pose_error_deg, ranges.pose_error_deg)))
    cx, cy, cz = (float(v) for v in com)
    mass_scale = ranges.mass_scale.draw(rng)
    if cameras:  # perception's own pose error replaces the drawn one
        error = PoseError()
    return ExecutionWorld("real", seed, physics, mass_scale, (cx, cy, cz), error, cameras)

"""The world a plan is executed in, drawn apart from what the planner knows.

The planner knows nominal physics (`PhysicsParams()`), the object's model and the pose it is told.
A real robot meets an object whose friction, mass and centre of mass differ from the model's,
standing a little away from where perception put it, and an arm whose controller tracks a little
differently. `sample_world(level, seed, ...)` draws one such execution world per trial:

- `exact`: the planner's world itself (the execution is the rollout's physics at the bridge's solver
  settings, the told pose is the true pose): the committed results before execution worlds existed;
- `real` (the evaluation's default): every quantity below drawn uniformly from its range;
- `mujoco`: the trial executes in MuJoCo (`shared.execution.robots.mujoco`), with that engine's own
  draws (`MujocoDraw`, second table) besides the `real` ones.

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
| camera extrinsics (each of the 3 cameras) | as calibrated | ±3 mm along, ±0.3° about each axis of the camera's frame | hand-eye / extrinsic calibration: a purpose-built point-cloud calibration reaches 0.3 mm and 0.25° (Flange-based 3D hand-eye calibration, arXiv 2407.16041); a routine checkerboard AX = XB calibration of a consumer depth camera (OpenCV `calibrateHandEye`; the methods compared by Enebuse et al., "Accuracy evaluation of hand-eye calibration techniques for vision-guided robots", PLOS ONE 2022) is good to a few mm and a few tenths of a degree. The range is an assumption between the two |

`mujoco` draws the same quantities from the same generator in the same order as `real` (so a seed gives
both levels the same friction, mass, pose and camera errors: the two engines are compared on common
draws), then MuJoCo's own, all carried to the MuJoCo robot as `MujocoDraw` (`TrueWorld.mujoco`):

| quantity (`MujocoDraw` field) | nominal (`MujocoConfig`) | `mujoco` range | what it rests on |
|---|---|---|---|
| object-table sliding friction (`table_friction`) | 0.5 | as `real` | as `real` |
| hand-object sliding friction (`hand_friction`) | 0.8 | as `real` | as `real` |
| per-finger friction (`finger_friction_scales`, index, middle, ring, thumb) | 1 | ×U(0.8, 1.2) each | an assumption: the pads of one hand differ by wear, dust and skin oil; no measurement of a hand's finger-to-finger spread was found |
| torsional friction (`torsional_friction_m`) | 0.005 m (MuJoCo's default) | U(0.001, 0.01) m | a torsional coefficient is about μ times the contact patch's radius; soft pads and an object's edge touch over patches of a few mm: an assumption from that estimate |
| rolling friction (`rolling_friction_m`) | 0 | as `real` | the same quantity (a length: torque per normal force) |
| object mass, centre of mass (`mass_scale`, `com_offset_m`) | model | as `real` | as `real` |
| arm servo stiffness (`arm_kp_scale`) | kp 2000 Nm/rad | ×U(0.7, 1.3) (the `real` position gain's draw) | as `real`'s position gain |
| arm servo damping (`arm_kv_scale`) | kv 150 Nm s/rad | ×U(0.7, 1.3) | an assumption: the same spread as the stiffness, drawn apart (a controller's damping is tuned with its stiffness, not locked to it) |
| command latency (`command_latency_s`) | 0 | as `real` | as `real` |
| finger servo stiffness (`finger_stiffness_scale`) | kp 3 Nm/rad | ×U(0.5, 1.5) | an assumption, wider than the arm's: a hand's position gains are set per hand (the LEAP's Dynamixel P gain is a register its software writes; the Allegro's PD gains are tuned by each lab), and the stiffness a fingertip shows falls with the current cap, the motor's temperature and gear backlash |
| finger damping (`finger_damping_scale`: the servo's kv and the joint's passive damping) | kv 0.1, passive 0.01 Nm s/rad | ×U(0.5, 1.5) | an assumption, as the finger stiffness |

`exact` draws no camera error; `real` and `mujoco` draw one per possible camera (3) after every other
`real` draw, so the `real` draws from before camera errors existed are unchanged. A camera truly stands at
its calibrated pose composed with its error (`CameraError.true_pose`): the capture renders from there
and the system back-projects with the calibrated pose (`shared.world.sim.camera.capture_object`).

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
from scipy.spatial.transform import Rotation

from shared.frames import make_transform, yaw_rotation
from shared.world.sim.params import REFERENCE_PARAMS, PhysicsParams

WorldLevel = Literal["exact", "real", "mujoco"]
WORLD_LEVELS: tuple[WorldLevel, ...] = ("exact", "real", "mujoco")
MAX_CAMERAS = 3  # `cameras` is 0-3: one extrinsic error is drawn for each camera there may be


@dataclass(frozen=True)
class Uniform:
    low: float
    high: float

    def draw(self, rng: np.random.Generator) -> float:
        return float(rng.uniform(self.low, self.high))


@dataclass(frozen=True)
class WorldRanges:
    """The `real` and `mujoco` levels' ranges (the module's tables say what each rests on)."""

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
    camera_translation_m: float = 0.003  # uniform in ±3 mm along each axis of the camera's frame
    camera_rotation_deg: float = 0.3  # uniform in ±0.3° about each axis of the camera's frame
    # The `mujoco` level's own.
    arm_damping_scale: Uniform = Uniform(0.7, 1.3)
    torsional_friction_m: Uniform = Uniform(0.001, 0.01)
    finger_stiffness_scale: Uniform = Uniform(0.5, 1.5)
    finger_damping_scale: Uniform = Uniform(0.5, 1.5)
    finger_friction_scale: Uniform = Uniform(0.8, 1.2)
    fingers: int = 4  # the Allegro's and the LEAP's: index, middle, ring, thumb


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
class CameraError:
    """Where a camera truly stands relative to its calibrated pose: a shift and a small turn (a rotation
    vector, degrees), both in the calibrated camera frame (OpenCV: x right, y down, z forward)."""

    translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def transform(self) -> np.ndarray:
        """T_calibrated_true: the true camera frame in the calibrated one."""
        rotation = Rotation.from_rotvec(np.radians(np.asarray(self.rotation_deg, dtype=np.float64))).as_matrix()
        return make_transform(rotation, np.asarray(self.translation_m, dtype=np.float64))

    def true_pose(self, T_world_camera: np.ndarray) -> np.ndarray:
        """T_world_camera of where the camera truly is, given its calibrated (nominal) pose."""
        true: np.ndarray = np.asarray(T_world_camera, dtype=np.float64) @ self.transform()
        return true


@dataclass(frozen=True)
class MujocoDraw:
    """The MuJoCo world's drawn physics (the module's second table): engine-neutral numbers, absolute
    coefficients or scales of the engine's nominal gains. A value outside its physical range (a negative
    friction or latency, a mass or gain scale <= 0, anything not finite) is refused with ValueError."""

    table_friction: float  # object-table sliding friction coefficient
    hand_friction: float  # hand-object sliding friction coefficient (palm, arm; each finger: times its scale)
    finger_friction_scales: tuple[float, ...]  # one per finger: index, middle, ring, thumb
    torsional_friction_m: float  # torque about the contact normal per newton of normal force
    rolling_friction_m: float  # rolling torque per newton of normal force
    mass_scale: float
    com_offset_m: tuple[float, float, float]  # in the object's frame O
    arm_kp_scale: float
    arm_kv_scale: float
    command_latency_s: float
    finger_stiffness_scale: float  # the hand servos' kp
    finger_damping_scale: float  # the hand servos' kv and the finger joints' passive damping

    def __post_init__(self) -> None:
        at_least_zero = {"table_friction": self.table_friction, "hand_friction": self.hand_friction,
                         "torsional_friction_m": self.torsional_friction_m,
                         "rolling_friction_m": self.rolling_friction_m, "command_latency_s": self.command_latency_s,
                         **{f"finger_friction_scales[{k}]": v for k, v in enumerate(self.finger_friction_scales)}}
        above_zero = {"mass_scale": self.mass_scale, "arm_kp_scale": self.arm_kp_scale,
                      "arm_kv_scale": self.arm_kv_scale, "finger_stiffness_scale": self.finger_stiffness_scale,
                      "finger_damping_scale": self.finger_damping_scale}
        for name, value in {**at_least_zero, **above_zero}.items():
            if not math.isfinite(value):
                raise ValueError(f"MujocoDraw.{name} must be finite, got {value}")
        for name, value in at_least_zero.items():
            if value < 0.0:
                raise ValueError(f"MujocoDraw.{name} must be >= 0, got {value}")
        for name, value in above_zero.items():
            if value <= 0.0:
                raise ValueError(f"MujocoDraw.{name} must be > 0, got {value}")
        if not self.finger_friction_scales:
            raise ValueError("MujocoDraw.finger_friction_scales needs one scale per finger, got none")
        if len(self.com_offset_m) != 3 or not all(math.isfinite(v) for v in self.com_offset_m):
            raise ValueError(f"MujocoDraw.com_offset_m must be 3 finite numbers, got {self.com_offset_m}")

    def record(self) -> dict[str, Any]:
        """The drawn values, rounded for a result record."""
        return {k: [round(x, 5) for x in v] if isinstance(v, tuple) else round(v, 5) for k, v in asdict(self).items()}


@dataclass(frozen=True)
class ExecutionWorld:
    """One drawn execution world: the physics the robot meets, the true object, the pose error, the
    cameras' extrinsic errors and (level `mujoco`) the MuJoCo world's own draw."""

    level: WorldLevel
    seed: int
    # PyBullet's physics. At level `mujoco`: the same draws in PyBullet's terms (what a PyBullet robot
    # handed this world meets, and what the record's common keys show); the MuJoCo robot reads `mujoco`.
    physics: PhysicsParams
    mass_scale: float = 1.0
    com_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # in the object's frame O
    pose_error: PoseError = PoseError()
    cameras: int = 0  # 0: the system is told the mesh (and a pose off by pose_error); 1-3: a camera cloud
    camera_errors: tuple[CameraError, ...] = ()  # one per possible camera (MAX_CAMERAS); none at level `exact`
    mujoco: MujocoDraw | None = None  # level `mujoco` only

    def record(self) -> dict[str, Any]:
        """What a result record keeps of the world (the drawn values, not the solver settings)."""
        p = self.physics
        return {"level": self.level, "seed": self.seed, "table_friction": round(p.table_friction, 4),
                "hand_friction": round(p.hand_friction, 4), "rolling_friction": round(p.object_rolling_friction, 5),
                "mass_scale": round(self.mass_scale, 4), "com_offset_m": [round(v, 4) for v in self.com_offset_m],
                "position_gain": round(p.arm_position_gain, 4), "latency_s": round(p.arm_command_latency_s, 4),
                "pose_error": {k: round(v, 4) for k, v in asdict(self.pose_error).items()}, "cameras": self.cameras,
                "camera_errors": [{"translation_m": [round(v, 5) for v in e.translation_m],
                                   "rotation_deg": [round(v, 4) for v in e.rotation_deg]} for e in self.camera_errors],
                "mujoco": None if self.mujoco is None else self.mujoco.record()}


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
    if cameras not in range(MAX_CAMERAS + 1):
        raise ValueError(f"cameras must be 0 (the mesh is told) or 1-{MAX_CAMERAS}, got {cameras}")
    if level == "exact":
        return ExecutionWorld("exact", seed, base, cameras=cameras)
    rng = np.random.default_rng(seed)
    # The order of these draws is the `real` worlds' since before camera errors and MuJoCo existed: a
    # seed's draws stay what they were. Whatever is added is drawn after them.
    table_scale = ranges.table_friction_scale.draw(rng)
    hand_scale = ranges.hand_friction_scale.draw(rng)
    rolling = ranges.rolling_friction.draw(rng)
    gain_scale = ranges.position_gain_scale.draw(rng)
    latency = ranges.command_latency_s.draw(rng)
    physics = replace(base, table_friction=base.table_friction * table_scale,
                      hand_friction=base.hand_friction * hand_scale, object_rolling_friction=rolling,
                      arm_position_gain=base.arm_position_gain * gain_scale, arm_command_latency_s=latency)
    fractions = np.array([ranges.com_offset_fraction_xy] * 2 + [ranges.com_offset_fraction_z])
    com = rng.uniform(-1.0, 1.0, 3) * fractions * np.asarray(half_extents_m, dtype=np.float64)
    dx, dy = (float(v) for v in rng.uniform(-ranges.pose_error_m, ranges.pose_error_m, 2))
    error = PoseError(dx, dy, float(rng.uniform(-ranges.pose_error_deg, ranges.pose_error_deg)))
    cx, cy, cz = (float(v) for v in com)
    mass_scale = ranges.mass_scale.draw(rng)
    camera_errors = tuple(_camera_error(rng, ranges) for _ in range(MAX_CAMERAS))
    if cameras:  # perception's own pose error replaces the drawn one
        error = PoseError()
    if level == "real":
        return ExecutionWorld("real", seed, physics, mass_scale, (cx, cy, cz), error, cameras, camera_errors)
    kv_scale = ranges.arm_damping_scale.draw(rng)
    torsional = ranges.torsional_friction_m.draw(rng)
    finger_kp_scale = ranges.finger_stiffness_scale.draw(rng)
    finger_kv_scale = ranges.finger_damping_scale.draw(rng)
    finger_friction = tuple(ranges.finger_friction_scale.draw(rng) for _ in range(ranges.fingers))
    draw = MujocoDraw(physics.table_friction, physics.hand_friction, finger_friction, torsional, rolling, mass_scale,
                      (cx, cy, cz), gain_scale, kv_scale, latency, finger_kp_scale, finger_kv_scale)
    return ExecutionWorld("mujoco", seed, physics, mass_scale, (cx, cy, cz), error, cameras, camera_errors, draw)


def _camera_error(rng: np.random.Generator, ranges: WorldRanges) -> CameraError:
    shift = rng.uniform(-ranges.camera_translation_m, ranges.camera_translation_m, 3)
    turn = rng.uniform(-ranges.camera_rotation_deg, ranges.camera_rotation_deg, 3)
    return CameraError((float(shift[0]), float(shift[1]), float(shift[2])), (float(turn[0]), float(turn[1]), float(turn[2])))

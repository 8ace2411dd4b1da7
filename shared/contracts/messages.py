"""Message contracts: every payload the system exchanges over Zenoh is one of these models.

Conventions
- Each message has `schema_version` (bumped on an incompatible change) and an `id`
  (request / job id; the dispatcher deduplicates on it, so ids make jobs idempotent).
- Arrays travel as `NDArray` (dtype + shape + raw little-endian bytes), never as lists. A field
  typed `NDArray` also accepts a numpy array, which is converted on construction.
- Every model is registered by class name in `MESSAGE_TYPES`; the codec looks types up there.
  Value types nested inside messages (`ObjectRef`, `ObjectPose`, `ScoreTerms`, ...) derive from
  `Value`: they carry no id and are not sent on their own.
- Each message type has `MAX_PAYLOAD_BYTES` (16 MiB by default, 64 MiB for batch results): the
  codec refuses a bigger payload before decoding it. A job's pose batch holds at most MAX_BATCH_POSES.
- Hand poses are 25-d vectors `[p(3), r6(6), q(16)]` of the hand base in the direction frame D
  (docs/architecture.md §Frames) unless a field name says `_world`. Units: metres, seconds, degrees where the
  field name says `_deg`.
"""
from __future__ import annotations

import hashlib
import math
import os
import uuid
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    FiniteFloat,
    Tag,
    field_validator,
    model_validator,
)

SCHEMA_VERSION = 1

MESSAGE_TYPES: dict[str, type[Message]] = {}

POSE_DIM = 25  # [p(3), r6(6), q(16)]
# The most poses one job carries: a generation batch, and the data engine validates one batch per
# ValidationJob (the planner sends 1-6 a job). 4096 poses are 0.8 MB as float64.
MAX_BATCH_POSES = 4096
# The largest encoded payload of a message (the codec and workers refuse bigger ones before decoding):
# room for the biggest legitimate request (a 4096-pose batch and an uploaded mesh of a few MB).
DEFAULT_MAX_PAYLOAD_BYTES = 16 * 2**20
# Results of a full batch (poses, per-term energies and histories, augmented copies) may be larger.
MAX_RESULT_PAYLOAD_BYTES = 64 * 2**20
# A library object id (rnd-042, pb-mug, proc-box-017, mesh-<hash>): never a path.
LIBRARY_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]*$"
HANDS: tuple[str, ...] = ("allegro", "leap")
ARMS: tuple[str, ...] = ("panda", "xarm7")
HAND_ARM_PAIRS: frozenset[tuple[str, str]] = frozenset({("allegro", "panda"), ("leap", "xarm7")})
MESH_FORMATS: tuple[str, ...] = ("obj", "stl", "ply", "glb")

Hand = Literal["allegro", "leap"]
Arm = Literal["panda", "xarm7"]
Sampler = Literal["ddpm", "ddim", "nearest"]  # nearest: the nearest-neighbour baseline (stored training poses)
DiffusionSampler = Literal["ddpm", "ddim"]
PoseMethod = Literal["gd2p", "nearest", "fixed", "fingertip"]
# How the executed plan is chosen among the candidates (PlannerOptions.choice):
# - "ranked": GD2P - plans rolled out with the arm and ranked by V = alpha L_goal + beta L_coll + gamma L_dir;
# - "unranked": the ranking ablation - the same stages and rollouts, the executed plan drawn at random
#   among the rolled-out ones (only the ranking score is removed);
# - "random": a random kinematically feasible pose, planned and executed with no prescreen, rollout or
#   ranking (the pose source's quality on its own).
PlanChoice = Literal["ranked", "unranked", "random"]
MAX_CORRECTIONS = 5  # corrective pushes per direction request
MAX_PHYSICS_DRAWS = 16  # rollouts per plan for robust ranking: each costs about half a second of CPU
# A resting-pose index on the bus (an object keeps at most 8 poses + its native one: shared.world.objects.geometry);
# the service checks it against the object's own count and answers bad_request beyond it.
MAX_RESTING_POSE_INDEX = 63
RestingPoseIndex = Annotated[int, Field(ge=0, le=MAX_RESTING_POSE_INDEX)]
SegmentLabel = Literal["approach", "push", "retreat"]
ExecutionStatus = Literal["idle", "executing", "done", "refused", "stopped", "error"]


def new_id() -> str:
    return uuid.uuid4().hex


class Message(BaseModel):
    """Base of every bus message."""

    model_config = ConfigDict(extra="forbid", frozen=False)
    schema_version: int = SCHEMA_VERSION  # a message whose shape changed incompatibly defaults to its own, higher
    id: str = Field(default_factory=new_id, min_length=1, max_length=128)

    MAX_PAYLOAD_BYTES: ClassVar[int] = DEFAULT_MAX_PAYLOAD_BYTES
    SCHEMA_CHANGE: ClassVar[str] = ""  # what changed in the message's last schema version (for the refusal)

    @classmethod
    def wire_schema(cls) -> int:
        """The schema version this build speaks for the message type."""
        version: int = cls.model_fields["schema_version"].default
        return version

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        MESSAGE_TYPES[cls.__name__] = cls


class Value(BaseModel):
    """Base of value types nested in messages (no id, not registered, never sent alone)."""

    model_config = ConfigDict(extra="forbid")


_ALLOWED_DTYPES = {"float32", "float64", "int32", "int64", "uint8", "uint16", "uint32", "int8", "int16", "bool"}
FLOAT_DTYPES: tuple[str, ...] = ("float32", "float64")
INT_DTYPES: tuple[str, ...] = ("int32", "int64")


class NDArray(BaseModel):
    """A numpy array as dtype + shape + little-endian bytes."""

    model_config = ConfigDict(extra="forbid")
    dtype: str
    shape: list[int]
    data: bytes

    @model_validator(mode="before")
    @classmethod
    def _accept_numpy(cls, value: Any) -> Any:
        if isinstance(value, np.ndarray):
            return _numpy_fields(value)
        return value

    @field_validator("dtype")
    @classmethod
    def _known_dtype(cls, v: str) -> str:
        if v not in _ALLOWED_DTYPES:
            raise ValueError(f"unsupported array dtype {v!r}; allowed: {sorted(_ALLOWED_DTYPES)}")
        return v

    @model_validator(mode="after")
    def _size_matches(self) -> NDArray:
        if any(d < 0 for d in self.shape):
            raise ValueError(f"negative dimension in shape {self.shape}")
        expected = int(np.prod(self.shape, dtype=np.int64)) * np.dtype(self.dtype).itemsize
        if expected != len(self.data):
            raise ValueError(f"array of shape {self.shape} and dtype {self.dtype} needs {expected} bytes, got {len(self.data)}")
        return self

    @classmethod
    def from_numpy(cls, a: np.ndarray) -> NDArray:
        return cls(**_numpy_fields(np.asarray(a)))

    def to_numpy(self) -> np.ndarray:
        little_endian = np.dtype(self.dtype).newbyteorder("<")
        array: np.ndarray = np.frombuffer(self.data, dtype=little_endian).reshape(self.shape).copy()
        return array


def _numpy_fields(a: np.ndarray) -> dict[str, Any]:
    dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
    a = np.ascontiguousarray(a, dtype=dt)
    return {"dtype": a.dtype.name, "shape": list(a.shape), "data": a.tobytes()}


def _format_shape(shape: tuple[int | None, ...]) -> str:
    names = iter("NMKT")
    return "[" + ", ".join(str(d) if d is not None else next(names, "?") for d in shape) + "]"


def array_of(
    shape: tuple[int | None, ...],
    dtypes: tuple[str, ...] = FLOAT_DTYPES,
    *,
    min_rows: int = 0,
    max_rows: int | None = None,
    finite: bool = True,
) -> AfterValidator:
    """A pydantic validator constraining an NDArray's shape (None = any size), dtype and values."""

    def check(a: NDArray) -> NDArray:
        if a.dtype not in dtypes:
            raise ValueError(f"array dtype must be one of {list(dtypes)}, got {a.dtype}")
        if len(a.shape) != len(shape) or any(want is not None and want != got
                                             for want, got in zip(shape, a.shape, strict=True)):
            raise ValueError(f"array shape must be {_format_shape(shape)}, got {a.shape}")
        if a.shape and a.shape[0] < min_rows:
            raise ValueError(f"array needs at least {min_rows} row(s), got shape {a.shape}")
        if max_rows is not None and a.shape and a.shape[0] > max_rows:
            raise ValueError(f"array has {a.shape[0]} rows; at most {max_rows} are accepted")
        if finite and a.dtype in FLOAT_DTYPES and not np.isfinite(a.to_numpy()).all():
            raise ValueError("array contains NaN or infinity")
        return a

    return AfterValidator(check)


PoseBatch = Annotated[NDArray, array_of((None, POSE_DIM), min_rows=1)]
"""[N >= 1, 25] hand poses."""
JobPoseBatch = Annotated[NDArray, array_of((None, POSE_DIM), min_rows=1, max_rows=MAX_BATCH_POSES)]
"""[1 <= N <= MAX_BATCH_POSES, 25] hand poses of one job."""
PoseArray = Annotated[NDArray, array_of((None, POSE_DIM))]
"""[N >= 0, 25] hand poses (may be empty)."""
Pose = Annotated[NDArray, array_of((POSE_DIM,))]
"""One 25-d hand pose."""
FloatVector = Annotated[NDArray, array_of((None,))]
"""[N] float values, one per pose."""
BoolVector = Annotated[NDArray, array_of((None,), ("bool",))]
"""[N] flags, one per pose."""
IndexVector = Annotated[NDArray, array_of((None,), INT_DTYPES)]
"""[N] integer indices."""
Vec3Batch = Annotated[NDArray, array_of((None, 3))]
"""[N, 3] vectors."""
PointCloud = Annotated[NDArray, array_of((None, 3), min_rows=1)]
"""[N >= 1, 3] points in metres."""
Matrix = Annotated[NDArray, array_of((None, None), min_rows=1)]
"""[T >= 1, D] float matrix."""

Seed = Annotated[int, Field(ge=0, le=2**63 - 1)]
NonNegFloat = Annotated[FiniteFloat, Field(ge=0.0)]
PositiveFloat = Annotated[FiniteFloat, Field(gt=0.0)]


def _rows(a: NDArray) -> int:
    return a.shape[0]


def _require_rows(owner: str, expected: int, **arrays: NDArray | None) -> None:
    for name, a in arrays.items():
        if a is not None and _rows(a) != expected:
            raise ValueError(f"{owner}: {name} has {_rows(a)} rows but there are {expected} poses")


def _unit(v: tuple[float, ...], name: str) -> tuple[float, ...]:
    """Normalise a vector; one already unit (to 1e-9) is kept as is, so a round trip is exact."""
    norm = math.sqrt(sum(c * c for c in v))
    if norm < 1e-9:
        raise ValueError(f"{name} must be a non-zero vector")
    if abs(norm - 1.0) <= 1e-9:
        return tuple(v)
    return tuple(c / norm for c in v)


def _check_pair(hand: str, arm: str) -> None:
    if (hand, arm) not in HAND_ARM_PAIRS:
        pairs = ", ".join(sorted(f"{h}+{a}" for h, a in HAND_ARM_PAIRS))
        raise ValueError(f"hand {hand!r} cannot be mounted on arm {arm!r}; supported pairs: {pairs}")


# ---------------------------------------------------------------------------------------------
# Generic replies and worker health
# ---------------------------------------------------------------------------------------------


class ErrorReply(Message):
    """What a service answers instead of a result when a request cannot be served.

    `code` is machine-readable: bad_request (malformed / unknown payload), not_implemented,
    infeasible, internal, timeout, unavailable, cancelled (the caller gave up: its lease was lost), busy (the
    worker's queue is full: nothing was queued, try again later), not_confirmed (the robot bridge held the plan
    for an operator's confirmation (`gd2p up --confirm`) and none came in time: nothing moved; not retried),
    lost (the robot's object tracker lost the object during or after a push: the system does not know where
    it is, so it neither judges nor corrects the push; look, and ask again).
    """

    code: str
    message: str
    request_type: str | None = None
    service: str | None = None

    CODES: ClassVar[tuple[str, ...]] = ("bad_request", "not_implemented", "infeasible", "internal", "timeout", "unavailable",
                                         "cancelled", "busy", "not_confirmed", "lost")


class HealthQuery(Message):
    """Ask a worker how it is."""


class WorkerStatus(Message):
    """A worker's answer to a health query (and what `gd2p status` aggregates)."""

    service: str
    worker_id: str
    pid: int
    host: str
    state: str = "ready"  # ready | busy | stopping
    in_flight: int = 0
    jobs_done: int = 0
    jobs_failed: int = 0
    uptime_s: float = 0.0
    capabilities: list[str] = Field(default_factory=list)


# ---------------------------------------------------------------------------------------------
# Objects, poses and frames
# ---------------------------------------------------------------------------------------------


class MeshBlob(Value):
    """A user mesh file (metres) identified by the SHA-256 of its bytes."""

    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    format: Literal["obj", "stl", "ply", "glb"]
    data: bytes = Field(min_length=1)
    name: str | None = None

    @model_validator(mode="after")
    def _hash_matches(self) -> MeshBlob:
        actual = hashlib.sha256(self.data).hexdigest()
        if actual != self.sha256:
            raise ValueError(f"mesh sha256 {self.sha256[:12]}... does not match its data (actual {actual[:12]}...)")
        return self

    @classmethod
    def from_bytes(cls, data: bytes, format: str, name: str | None = None) -> MeshBlob:
        return cls(sha256=hashlib.sha256(data).hexdigest(), format=format, data=data, name=name)

    @classmethod
    def from_file(cls, path: str) -> MeshBlob:
        """Read a mesh file; the format is taken from the file extension."""
        ext = os.path.splitext(path)[1].lower().lstrip(".")
        if ext not in MESH_FORMATS:
            raise ValueError(f"{path}: unsupported mesh format {ext!r}; supported: {list(MESH_FORMATS)}")
        with open(path, "rb") as f:
            return cls.from_bytes(f.read(), ext, name=os.path.basename(path))


class ObjectRef(Value):
    """An object: exactly one of a library id, a mesh file, or a point cloud (metres)."""

    library_id: str | None = Field(default=None, min_length=1, max_length=128, pattern=LIBRARY_ID_PATTERN)
    mesh: MeshBlob | None = None
    point_cloud: PointCloud | None = None
    scale: PositiveFloat | None = None

    @field_validator("library_id")
    @classmethod
    def _not_a_path(cls, v: str | None) -> str | None:
        if v is not None and ".." in v:
            raise ValueError(f"library_id must be a library object id, not a path; got {v!r}")
        return v

    @model_validator(mode="after")
    def _exactly_one_source(self) -> ObjectRef:
        given = [n for n in ("library_id", "mesh", "point_cloud") if getattr(self, n) is not None]
        if len(given) != 1:
            raise ValueError(f"an object needs exactly one of library_id, mesh, point_cloud; got {given or 'none'}")
        return self

    @property
    def object_id(self) -> str:
        """A stable id: the library id, `mesh:<sha256[:16]>` or `cloud:<sha256[:16]>`."""
        if self.library_id is not None:
            return self.library_id
        if self.mesh is not None:
            return f"mesh:{self.mesh.sha256[:16]}"
        assert self.point_cloud is not None
        return f"cloud:{hashlib.sha256(self.point_cloud.data).hexdigest()[:16]}"


class ObjectPose(Value):
    """An object pose in the world: position (m) and unit quaternion (x, y, z, w)."""

    position: tuple[FiniteFloat, FiniteFloat, FiniteFloat]
    quaternion_xyzw: tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat] = (0.0, 0.0, 0.0, 1.0)

    @field_validator("quaternion_xyzw")
    @classmethod
    def _normalise(cls, q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        return _unit(q, "quaternion_xyzw")  # type: ignore[return-value]


class ObjectPath(Value):
    """An object's poses over time: plan times (s), positions [T, 3] (m) and unit quaternions [T, 4] (x, y, z, w)."""

    times_s: FloatVector
    positions: Matrix
    quaternions_xyzw: Matrix

    @model_validator(mode="after")
    def _consistent(self) -> ObjectPath:
        n = self.times_s.shape[0]
        if tuple(self.positions.shape) != (n, 3) or tuple(self.quaternions_xyzw.shape) != (n, 4):
            raise ValueError(f"ObjectPath: {n} times need positions [{n}, 3] and quaternions_xyzw [{n}, 4], got "
                             f"{self.positions.shape} and {self.quaternions_xyzw.shape}")
        if np.any(np.diff(self.times_s.to_numpy()) <= 0):
            raise ValueError("ObjectPath: times_s must increase strictly")
        return self


class DirectionFrame(Value):
    """Where the object is and which way to push it: defines the direction frame D."""

    object_pose: ObjectPose
    yaw_deg: FiniteFloat | None = None
    direction_xy: tuple[FiniteFloat, FiniteFloat] | None = None

    @field_validator("direction_xy")
    @classmethod
    def _normalise(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        return None if v is None else _unit(v, "direction_xy")  # type: ignore[return-value]

    @model_validator(mode="after")
    def _one_direction(self) -> DirectionFrame:
        if (self.yaw_deg is None) == (self.direction_xy is None):
            raise ValueError("give exactly one of yaw_deg or direction_xy for the push direction")
        return self

    def yaw_rad(self) -> float:
        """The push direction as a yaw angle in the world (radians)."""
        if self.yaw_deg is not None:
            return math.radians(self.yaw_deg)
        assert self.direction_xy is not None
        return math.atan2(self.direction_xy[1], self.direction_xy[0])


class CircleObstacle(Value):
    """A vertical cylinder obstacle on the table: centre (x, y), radius and height in metres. Nothing may touch it:
    not the robot, not the pushed object (it may be fragile, or someone's cup)."""

    x: FiniteFloat
    y: FiniteFloat
    radius: PositiveFloat
    height_m: PositiveFloat = Field(default=0.3, le=2.0)


class WallObstacle(Value):
    """A straight wall standing on the table (a shelf's side, a bin's edge, a fixture): a box `length_m` long
    along the direction `yaw_deg` (degrees about world z), `thickness_m` thick and `height_m` tall, centred at
    (x, y). The pushed object may slide along it (a wall is there to be pushed against); the robot must not
    touch it. The cameras see it, and the system cuts it from what they see as a known part of the workcell."""

    x: FiniteFloat
    y: FiniteFloat
    yaw_deg: FiniteFloat = 0.0
    length_m: PositiveFloat = Field(le=3.0)
    thickness_m: PositiveFloat = Field(default=0.02, le=0.5)
    height_m: PositiveFloat = Field(default=0.15, le=1.0)


def _obstacle_kind(value: Any) -> str:
    """A wall has a length, a cylinder a radius: which of the two a message's obstacle is (its errors are then that
    kind's alone)."""
    fields = value if isinstance(value, dict) else vars(value)
    return "wall" if "length_m" in fields else "circle"


# An obstacle of a request or a world: told apart by their fields (old messages carry circles alone).
Obstacle = Annotated[Annotated[CircleObstacle, Tag("circle")] | Annotated[WallObstacle, Tag("wall")],
                     Discriminator(_obstacle_kind)]


# ---------------------------------------------------------------------------------------------
# Generation
# ---------------------------------------------------------------------------------------------


class GenerationJob(Message):
    """Optimise a batch of pre-contact push poses (or grasp poses) for one object and hand."""

    object: ObjectRef
    hand: Hand
    batch_size: int = Field(ge=1, le=MAX_BATCH_POSES)
    seed: Seed = 0
    iterations: int | None = Field(default=None, ge=1, le=100_000)
    contacts_per_pose: int | None = Field(default=None, ge=1, le=64)
    grasp_only: bool = False  # grasp terms only (no E_dir / E_arm): the grasp-pose baseline
    # The object's placement in D: resting in `pose_index` (None: its default resting pose), turned by
    # `yaw_rad` about D's z (`ObjectModel.T_D_O(pose_index, yaw_rad)`). The defaults are the placement every
    # caller used before (default pose, yaw 0); a ValidationJob places the object the same way with the same
    # `pose_index` and a `frame` turned by the same yaw (the data engine's random placements).
    pose_index: RestingPoseIndex | None = None
    yaw_rad: FiniteFloat = Field(default=0.0, ge=-2 * math.pi, le=2 * math.pi)


class GenerationResult(Message):
    """The optimised poses of one generation job (in D) with their per-term energies."""

    job_id: str
    hand: Hand
    object_id: str
    poses: PoseBatch
    energies: dict[str, FloatVector]
    palm_normals: Vec3Batch
    max_penetration_m: FloatVector
    elapsed_s: NonNegFloat
    energy_history: dict[str, FloatVector] = Field(default_factory=dict)  # batch-mean per iteration

    MAX_PAYLOAD_BYTES: ClassVar[int] = MAX_RESULT_PAYLOAD_BYTES

    @model_validator(mode="after")
    def _consistent_rows(self) -> GenerationResult:
        b = _rows(self.poses)
        _require_rows("GenerationResult", b, palm_normals=self.palm_normals, max_penetration_m=self.max_penetration_m)
        _require_rows("GenerationResult", b, **{f"energies[{k}]": v for k, v in self.energies.items()})
        return self


# ---------------------------------------------------------------------------------------------
# Validation and arm rollouts
# ---------------------------------------------------------------------------------------------


class PhysicsSettings(Value):
    """Push-simulation settings; the validator's measured defaults apply when omitted."""

    solver_iterations: int = Field(ge=1, le=1000)
    time_step_s: PositiveFloat = Field(le=0.1)
    push_speed_mps: PositiveFloat = Field(le=2.0)


class PlanSegment(Value):
    """A labelled index range [start, stop) of a plan's waypoints."""

    label: SegmentLabel
    start: int = Field(ge=0)
    stop: int = Field(ge=1)

    @model_validator(mode="after")
    def _ordered(self) -> PlanSegment:
        if self.stop <= self.start:
            raise ValueError(f"segment {self.label!r} has stop {self.stop} <= start {self.start}")
        return self


class Plan(Message):
    """A timed joint trajectory of arm (+ hand) joints with labelled approach/push/retreat segments."""

    arm: Arm
    hand: Hand
    joint_names: list[str] = Field(min_length=1)
    positions: Matrix
    times_s: FloatVector
    segments: list[PlanSegment] = Field(default_factory=list)

    @model_validator(mode="after")
    def _consistent(self) -> Plan:
        _check_pair(self.hand, self.arm)
        if len(set(self.joint_names)) != len(self.joint_names):
            raise ValueError("plan joint_names contain duplicates")
        steps, dof = self.positions.shape
        if dof != len(self.joint_names):
            raise ValueError(f"plan positions have {dof} columns but there are {len(self.joint_names)} joint names")
        if self.times_s.shape[0] != steps:
            raise ValueError(f"plan has {steps} waypoints but {self.times_s.shape[0]} times")
        times = self.times_s.to_numpy()
        if steps and times[0] < 0:
            raise ValueError("plan times must start at or after 0")
        if np.any(np.diff(times) <= 0):
            raise ValueError("plan times_s must be strictly increasing")
        previous_stop = 0
        for seg in self.segments:
            if seg.start < previous_stop or seg.stop > steps:
                raise ValueError(f"segment {seg.label!r} [{seg.start}, {seg.stop}) overlaps another or exceeds {steps} waypoints")
            previous_stop = seg.stop
        return self


class ValidationJob(Message):
    """Validate hand poses by a simulated push (floating hand, or with the arm following a plan)."""

    object: ObjectRef
    hand: Hand
    poses: JobPoseBatch
    seed: Seed = 0
    push_distance_m: PositiveFloat = Field(default=0.20, le=1.0)
    settings: PhysicsSettings | None = None
    augment: bool = False  # also validate 10 scrambled-Halton perturbations of each success
    with_arm: bool = False  # roll out `plan` with the arm instead of a floating hand
    arm: Arm | None = None
    plan: Plan | None = None
    # The object's world pose and push direction: required for arm rollouts; for a floating hand it
    # places the object (in resting pose `pose_index`) turned in D as the frame says (default: yaw 0 in D).
    frame: DirectionFrame | None = None
    # Floating hand only: the object's resting pose (None: its default one). With a frame, the frame's
    # object must be this resting pose turned about the vertical (the validator refuses it otherwise).
    pose_index: RestingPoseIndex | None = None
    obstacles: list[Obstacle] = Field(default_factory=list)
    # Arm rollouts: also roll the plan out in this many worlds drawn around the nominal physics and
    # the told pose (`shared.world.sim.world.rollout_worlds`, seeded by `seed`), for ranking by robustness.
    physics_draws: int = Field(default=0, ge=0, le=MAX_PHYSICS_DRAWS)

    @model_validator(mode="after")
    def _rollout_complete(self) -> ValidationJob:
        rollout_fields = {"arm": self.arm, "plan": self.plan}
        if self.physics_draws and not self.with_arm:
            raise ValueError("physics_draws is only used with with_arm=True (arm rollouts)")
        if self.with_arm:
            if self.pose_index is not None:
                raise ValueError("pose_index places the object for a floating hand; an arm rollout places it at "
                                 "frame.object_pose")
            missing = [n for n, v in {**rollout_fields, "frame": self.frame}.items() if v is None]
            if missing:
                raise ValueError(f"with_arm=True needs {', '.join(missing)}")
            _check_pair(self.hand, self.arm)  # type: ignore[arg-type]
            if self.plan is not None and (self.plan.arm, self.plan.hand) != (self.arm, self.hand):
                raise ValueError(f"plan is for {self.plan.hand}+{self.plan.arm}, job is for {self.hand}+{self.arm}")
            if _rows(self.poses) != 1:
                raise ValueError(f"an arm rollout validates one plan and its one pose, got {_rows(self.poses)} poses")
            if self.augment:
                raise ValueError("augment is not supported for arm rollouts")
        else:
            given = [n for n, v in rollout_fields.items() if v is not None]
            if given:
                raise ValueError(f"{', '.join(given)} only used with with_arm=True (arm rollouts)")
        return self


class PushOutcomes(Value):
    """Per-pose outcomes of simulated pushes (all arrays have one row per pose)."""

    success: BoolVector
    position_error_m: FloatVector
    rotation_deg: FloatVector
    max_tilt_deg: FloatVector
    contact_kept: BoolVector
    hand_table_contact: BoolVector
    initial_penetration_m: FloatVector

    def _outcome_rows(self, owner: str) -> int:
        n = _rows(self.success)
        _require_rows(
            owner,
            n,
            position_error_m=self.position_error_m,
            rotation_deg=self.rotation_deg,
            max_tilt_deg=self.max_tilt_deg,
            contact_kept=self.contact_kept,
            hand_table_contact=self.hand_table_contact,
            initial_penetration_m=self.initial_penetration_m,
        )
        return n


class AugmentedOutcomes(PushOutcomes):
    """Halton perturbations of successful poses, each with its parent's index and its outcome."""

    poses: PoseArray
    parent_index: IndexVector

    @model_validator(mode="after")
    def _consistent_rows(self) -> AugmentedOutcomes:
        n = self._outcome_rows("AugmentedOutcomes")
        _require_rows("AugmentedOutcomes", n, poses=self.poses, parent_index=self.parent_index)
        return self


class ValidationResult(PushOutcomes, Message):
    """Outcomes of a validation job, one row per job pose (plus augmented poses if asked)."""

    job_id: str
    hand: Hand
    object_id: str
    augmented: AugmentedOutcomes | None = None
    goal_error_m: FloatVector | None = None  # arm rollouts: L_goal
    collision_cost: FloatVector | None = None  # arm rollouts: L_coll
    obstacle_contact: BoolVector | None = None  # arm rollouts: the robot or the pushed object touched an obstacle
    final_object_poses: list[ObjectPose] | None = None  # arm rollouts: object pose after the push
    # Arm rollouts: the object's path while the plan was played (plan times), what a closed-loop
    # execution compares the tracked object with.
    object_paths: list[ObjectPath] | None = None
    # Arm rollouts with physics_draws: the push's outcome in each drawn world (one row per draw).
    draws: PushOutcomes | None = None
    elapsed_s: NonNegFloat = 0.0

    MAX_PAYLOAD_BYTES: ClassVar[int] = MAX_RESULT_PAYLOAD_BYTES

    @model_validator(mode="after")
    def _consistent_rows(self) -> ValidationResult:
        n = self._outcome_rows("ValidationResult")
        _require_rows("ValidationResult", n, goal_error_m=self.goal_error_m, collision_cost=self.collision_cost,
                      obstacle_contact=self.obstacle_contact)
        if self.final_object_poses is not None and len(self.final_object_poses) != n:
            raise ValueError(f"ValidationResult: final_object_poses has {len(self.final_object_poses)} entries but there are {n} poses")
        if self.object_paths is not None and len(self.object_paths) != n:
            raise ValueError(f"ValidationResult: object_paths has {len(self.object_paths)} entries but there are {n} poses")
        if self.draws is not None:
            self.draws._outcome_rows("ValidationResult.draws")
        return self


# ---------------------------------------------------------------------------------------------
# Sampling
# ---------------------------------------------------------------------------------------------


class SampleRequest(Message):
    """Sample K push poses for an object in a direction frame.

    `sampler` "ddpm" / "ddim": the diffusion model; "nearest": the stored poses of the training frame
    nearest in BPS space (a seeded subset of K, or all of them when it has fewer).
    """

    object: ObjectRef
    hand: Hand
    frame: DirectionFrame
    k: int = Field(default=200, ge=1, le=1000)
    sampler: Sampler = "ddpm"
    steps: int | None = Field(default=None, ge=1, le=1000)  # denoising steps (DDIM); None = sampler default
    seed: Seed = 0
    # The diffusion samplers' temperature (initial and step noise multiplied by it); None = the service's
    # default (shared.sampling.diffusion.default_noise_scale). Not for "nearest".
    noise_scale: float | None = Field(default=None, gt=0.0, le=1.0)
    # Whether to score the poses with the success critic (SampleResponse.success_probability): its contact
    # features cost 24-35 ms per 200 poses, so a planner that will not order by the critic skips them.
    score: bool = True
    # Steer the diffusion samples up the success critic's log P(success) in their last `guided_steps` denoising
    # steps, each moving a pose by this scale x the gradient in normalised units (shared/sampling/guidance.py);
    # None: plain samples. 0.02 was chosen on val objects (docs/evaluation.md §Tuned settings); ~0.2 s per guided
    # step per 200 poses on one thread. Needs a critic made for the sampler's checkpoint; not for "nearest".
    critic_guidance: float | None = Field(default=None, gt=0.0, le=1.0)
    guided_steps: int = Field(default=10, ge=1, le=100)


class SampleResponse(Message):
    """Sampled poses, in D and in the world, with the checkpoint (or NN index) that produced them.

    K rows for the diffusion samplers; for "nearest" at most K (all the matched frame has, when fewer).
    """

    request_id: str
    hand: Hand
    poses_d: PoseBatch
    poses_world: PoseBatch
    latency_s: NonNegFloat
    checkpoint_id: str
    sampler: Sampler = "ddpm"
    noise_scale: float | None = None  # the diffusion samplers' temperature the poses were drawn with
    # Per pose: the success critic's P(a floating-hand push from it succeeds), for a nearest-neighbour match too
    # (scored from the object as the diffusion sampler encodes it); None when the service has no critic for the
    # hand's checkpoint or the request did not ask for scores.
    success_probability: FloatVector | None = None

    @model_validator(mode="after")
    def _consistent_rows(self) -> SampleResponse:
        _require_rows("SampleResponse", _rows(self.poses_d), poses_world=self.poses_world,
                      success_probability=self.success_probability)
        return self


# ---------------------------------------------------------------------------------------------
# Push requests
# ---------------------------------------------------------------------------------------------


class PlannerOptions(Value):
    """How the planner answers a push request: every knob, each defaulting to the planner's default.

    This class is the one definition of that default (docs/usage.md "The planner's default"); the evaluation's
    methods (evaluation/methods.yaml) name only what they change from it.
    """

    # Where candidate poses come from: the diffusion sampler, the nearest-neighbour baseline (sampler
    # service), the fixed spatula pose (the paper's baselines) or one fingertip pointing along the push (a
    # straight-line pusher), for comparisons.
    method: PoseMethod = "gd2p"
    # The diffusion sampler for method "gd2p": the paper's DDPM-100, or the DDIM-10 fast path (fewer denoising
    # steps; its poses validate about as often: docs/results.md).
    sampler: DiffusionSampler = "ddpm"
    k: int = Field(default=200, ge=1, le=1000)  # candidate poses drawn per push
    # Consider the samples (the model's, or for method "nearest" the retrieved ones) in the order of the sampler's
    # success critic (when it has one for its checkpoint and scored them) instead of the best-aligned palms first
    # (L_dir, the paper's order). Chosen on the val objects (docs/evaluation.md §Tuned settings).
    critic: bool = True
    # SampleRequest.critic_guidance for the diffusion samples (None: plain samples; guidance has not been
    # measured in the trial experiments as the default).
    critic_guidance: float | None = Field(default=None, gt=0.0, le=1.0)
    # Push `PipelineSettings.prescreen` of the first feasible poses with a floating hand before planning (the
    # prescreen). False is the fast path (with sampler "ddim"): less time to plan, some success lost, so not the
    # default (docs/evaluation.md §Tuned settings).
    prescreen: bool = True
    # "ranked" (GD2P), "unranked" (the ranking ablation: same stages, a rolled-out plan drawn at random) or
    # "random" (a random feasible pose, no prescreen or rollouts).
    choice: PlanChoice = "ranked"
    # Rank by robustness: roll each plan out in this many physics draws besides the nominal world
    # (friction, mass, centre of mass, controller, pose off by up to 1 cm / 5 deg; `shared.world.sim.world`)
    # and score its mean L_goal. 0: the paper's single nominal rollout.
    physics_draws: int = Field(default=0, ge=0, le=MAX_PHYSICS_DRAWS)
    # Closed loop at the scale of pushes (direction requests; a goal_xy request does not use it: each of
    # its pushes is already planned from where the object was seen, up to max_steps): when the executed
    # push leaves the object more than the success tolerance from the target but upright and turned no
    # more than the success bound allows, push again from where the robot bridge observed it, up to this
    # many times. Needs the object's pose after each push: the simulated robot's tracker sees it; on
    # hardware a tracker must publish it on gd2p/robot_bridge/object_track (docs/interfaces.md).
    corrections: int = Field(default=2, ge=0, le=MAX_CORRECTIONS)
    # Watch the object while each push runs (the robot bridge's object tracking) and stop the push when it
    # strays from the path the chosen plan's rollout predicted (shared/planning/monitor.py); the push is
    # backed out and, within `corrections`, pushed again from where the object was seen. Plans chosen
    # with choice "random" have no rollout to follow and run open loop.
    closed_loop: bool = True
    max_steps: int = Field(default=10, ge=1, le=100)  # a goal_xy request's pushes at most

    @model_validator(mode="after")
    def _consistent(self) -> PlannerOptions:
        if self.critic_guidance is not None and self.method != "gd2p":
            raise ValueError(f"critic_guidance steers the diffusion samples; method {self.method!r} draws none")
        if self.physics_draws and self.choice == "random":
            raise ValueError("physics_draws ranks rolled-out plans; choice 'random' rolls none out")
        return self


PUSH_REQUEST_SCHEMA = 2


class PushRequest(Message):
    """Push or pull an object: a direction and distance, or a goal point or pose (multi-step). The question a
    user asks; how the planner answers it is `options` (its default when left out)."""

    SCHEMA_CHANGE: ClassVar[str] = (
        "schema 2 keeps the question at the top (object, object_pose, direction_deg or goal_xy (with goal_yaw_deg), "
        "distance_m, hand, arm, obstacles, seed, client_lease) and moves every planner knob into `options` (PlannerOptions: "
        f"{', '.join(PlannerOptions.model_fields)}); see docs/interfaces.md")

    schema_version: int = PUSH_REQUEST_SCHEMA
    object: ObjectRef
    # None: resting at a reachable spot in front of the robot; for a point cloud, where the cloud shows it.
    object_pose: ObjectPose | None = None
    direction_deg: FiniteFloat | None = None
    goal_xy: tuple[FiniteFloat, FiniteFloat] | None = None
    # With goal_xy, a pose goal: the yaw (degrees, about the world z axis) the object is to end with, resting as
    # it stands at the start: that resting pose turned by this much about world z, the yaw `object_pose` has when
    # `gd2p push --yaw` places the object (for an object standing as modelled, the yaw of its frame O). The request
    # then succeeds with the object within 2 cm and 15 deg of that pose instead of within 3 cm of the point
    # (shared/world/push_outcome.py: YawGoal).
    goal_yaw_deg: FiniteFloat | None = None
    distance_m: PositiveFloat = Field(default=0.20, le=1.0)  # with goal_xy: the longest single push
    hand: Hand = "allegro"
    arm: Arm = "panda"
    obstacles: list[Obstacle] = Field(default_factory=list)
    seed: Seed = 0
    # The client's lease (`gd2p/lease/client/<identity>/<id>`, shared/bus/lease.py): when it is lost (Ctrl-C, a
    # crashed client, a lost connection) the planner cancels the request, stopping the robot if it moves. The
    # planner refuses a request without one (every push moves the robot).
    client_lease: str | None = Field(default=None, min_length=1, max_length=256)
    options: PlannerOptions = Field(default_factory=PlannerOptions)

    @model_validator(mode="before")
    @classmethod
    def _knobs_in_options(cls, data: Any) -> Any:
        if isinstance(data, dict):
            misplaced = [name for name in PlannerOptions.model_fields if name in data]
            if misplaced:
                raise ValueError(f"{', '.join(misplaced)} belong in `options` since PushRequest schema 2: "
                                 f"{cls.SCHEMA_CHANGE}")
        return data

    @model_validator(mode="after")
    def _target_and_robot(self) -> PushRequest:
        if (self.direction_deg is None) == (self.goal_xy is None):
            raise ValueError("give exactly one of direction_deg or goal_xy")
        if self.goal_yaw_deg is not None and self.goal_xy is None:
            raise ValueError("goal_yaw_deg needs goal_xy: a yaw goal is the yaw of a pose goal (goal_xy, goal_yaw_deg)")
        if self.object.point_cloud is not None and self.object_pose is not None:
            raise ValueError("a point cloud shows where the object stands: leave object_pose empty")
        _check_pair(self.hand, self.arm)
        return self


class ScoreTerms(Value):
    """The ranking score V = alpha L_goal + beta L_coll + gamma L_dir and its terms."""

    l_goal: FiniteFloat
    l_coll: FiniteFloat
    l_dir: FiniteFloat
    v: FiniteFloat
    alpha: FiniteFloat
    beta: FiniteFloat
    gamma: FiniteFloat
    # Ranked by robustness: in how many of the rollout's physics draws (the nominal world included) the
    # push succeeded, out of how many; L_goal is then their mean.
    draws_succeeded: int | None = Field(default=None, ge=0)
    draws: int | None = Field(default=None, ge=1)


class ExecutionResult(Value):
    """What happened to the object when a plan was executed."""

    final_object_pose: ObjectPose
    position_error_m: NonNegFloat
    rotation_deg: NonNegFloat
    toppled: bool
    success: bool
    contact_kept: bool | None = None
    # A pose goal's (PushRequest.goal_yaw_deg): how far the object's final yaw is from the goal yaw, degrees (0-180).
    yaw_error_deg: NonNegFloat | None = Field(default=None, le=180.0)


class PushStep(Value):
    """One push of a multi-step request."""

    chosen_pose: Pose  # in D
    chosen_pose_world: Pose
    plan: Plan
    score: ScoreTerms | None = None  # None when ranking is off
    result: ExecutionResult
    # Why this push was made, when it is not the request's first: e.g. a correction, with how far from
    # the target the object was left.
    reason: str | None = Field(default=None, max_length=500)
    # Why the closed-loop monitor stopped this push before its end (it was then backed out along its way in).
    stopped: str | None = Field(default=None, max_length=500)


class PushResponse(Message):
    """The outcome of a push request: chosen pose and plan, score, execution result, recording."""

    request_id: str
    success: bool
    chosen_pose: Pose  # first push, in D
    chosen_pose_world: Pose
    plan: Plan
    score: ScoreTerms | None = None  # None when ranking is off
    result: ExecutionResult  # the final outcome of the whole request
    steps: list[PushStep] = Field(default_factory=list)  # every push of a multi-step request
    # What else the user should know, e.g. why a correction the request allowed was not made.
    notes: list[str] = Field(default_factory=list)
    recording_path: str | None = None
    timings_s: dict[str, NonNegFloat] = Field(default_factory=dict)  # by stage: sampling, ik, planning, ...


# ---------------------------------------------------------------------------------------------
# Robot bridge
# ---------------------------------------------------------------------------------------------


class SimWorld(Value):
    """The world a simulated robot starts from: the object at its pose, obstacles, the robot at home."""

    object: ObjectRef
    object_pose: ObjectPose  # frame O (centre of mass, principal axes) in the world
    obstacles: list[Obstacle] = Field(default_factory=list)


class ExecutionCommand(Message):
    """Execute a plan; `lease_token` is the commander's liveliness key, whose loss stops motion.

    `world` (for the simulated backend; a real robot lives in the real world) resets the simulation to it
    before executing; without it the plan runs in the world as the previous command left it.
    """

    plan: Plan
    lease_token: str = Field(min_length=1)
    realtime_factor: PositiveFloat = Field(default=1.0, le=1000.0)
    world: SimWorld | None = None


class ExecutionState(Message):
    """The robot's joint state (and object pose, if observed) at a time, with the execution status."""

    stamp: FiniteFloat  # seconds since the Unix epoch
    joint_names: list[str]
    positions: FloatVector
    velocities: FloatVector
    object_pose: ObjectPose | None = None  # the tracker's latest pose of the object, when one is seen
    # Why the robot's tracker has no pose of the object now (an image tracker lost it: too few points, a poor
    # fit); set only when object_pose is None. A closed loop stops a push on it rather than push on a stale pose.
    object_lost: str | None = Field(default=None, max_length=300)
    status: ExecutionStatus = "idle"
    command_id: str | None = None
    message: str = ""
    plan_time_s: NonNegFloat | None = None  # while a plan runs: how far into the plan's own time the robot is

    @model_validator(mode="after")
    def _consistent(self) -> ExecutionState:
        n = len(self.joint_names)
        for name in ("positions", "velocities"):
            if getattr(self, name).shape[0] != n:
                raise ValueError(f"ExecutionState: {name} has {getattr(self, name).shape[0]} values for {n} joints")
        return self


class ObjectTrack(Message):
    """The object's pose as a tracker saw it, while a plan runs (the simulated robot's tracker, or a user's
    tracker on hardware: see docs/interfaces.md)."""

    stamp: FiniteFloat  # seconds since the Unix epoch, when the pose was seen
    pose: ObjectPose
    source: str = Field(min_length=1, max_length=128)  # which tracker: "image-tracker", or the user's name for it
    command_id: str | None = None  # the command executing when it was seen, if the publisher knows it
    plan_time_s: NonNegFloat | None = None  # how far into that command's plan, if the publisher knows it
    fitness: float | None = Field(default=None, ge=0.0, le=1.0)  # a registering tracker's fit (share of points explained)


class EStop(Message):
    """Stop every robot backend at once."""

    reason: str = Field(min_length=1)
    issued_by: str | None = None


# ---------------------------------------------------------------------------------------------
# Preview and confirm (`gd2p up --confirm`): the bridge holds each plan until an operator confirms it
# ---------------------------------------------------------------------------------------------


class PlanHeld(Message):
    """A command the robot bridge holds until an operator confirms it (or `expires_at` passes: then it is
    dropped and the push answers "not confirmed"). Published on the bridge's held-plan key."""

    command_id: str = Field(min_length=1, max_length=128)
    plan: Plan
    expires_at: FiniteFloat  # seconds since the Unix epoch
    reason: str | None = Field(default=None, max_length=500)  # set when the hold ends: "confirmed", "expired", ...


class PlanConfirm(Message):
    """An operator's go for one held command (`gd2p confirm ID`, or the live view's button)."""

    command_id: str = Field(min_length=1, max_length=128)
    operator: str | None = Field(default=None, max_length=128)  # who confirmed, for the log and the recording


class PlanConfirmReply(Message):
    """The bridge's answer to a PlanConfirm: accepted (the held plan runs now) or why not (unknown id,
    expired, already confirmed, not an operator)."""

    command_id: str
    accepted: bool
    reason: str = ""


# ---------------------------------------------------------------------------------------------
# Launcher control
# ---------------------------------------------------------------------------------------------


class ScaleRequest(Message):
    """Bring a service to exactly `count` workers."""

    service: str = Field(min_length=1)
    count: int = Field(ge=0, le=1024)


class ScaleReply(Message):
    """The launcher's answer to a scale request: the new count and which workers changed."""

    service: str
    count: int = Field(ge=0)
    started: list[str] = Field(default_factory=list)
    stopped: list[str] = Field(default_factory=list)


# ---------------------------------------------------------------------------------------------
# Live view (`gd2p up --view`, `gd2p view`): what the planner decided, for people to watch
# ---------------------------------------------------------------------------------------------


class RolloutPreview(Value):
    """One rolled-out plan of a push: the plan, its rollout's L_goal / L_coll, and the object path it predicted."""

    plan: Plan
    goal_error_m: FiniteFloat | None = None
    collision_cost: FiniteFloat | None = None
    obstacle_contact: bool = False
    success: bool | None = None  # the rollout's push succeeded (nominal world)
    object_path: ObjectPath | None = None  # world frame, plan times


class PushDecision(Message):
    """What the planner considered and chose for one push, published just before the chosen plan goes to the
    robot bridge (the live view draws it; the push recording keeps it).

    `candidates_world`: the sampled hand poses of this push in the world ([N, 25]), `critic_scores` the success
    critic's P(success) per candidate (None when the sampler did not score them); `rollouts` the plans rolled out
    and ranked (empty for choice "random"); `chosen` the index among them of the executed plan (None: not one of
    them, e.g. a random choice), whose full plan (with its way back) is `plan`."""

    request_id: str | None = Field(default=None, max_length=128)
    push_index: int = Field(default=0, ge=0)  # the request's n-th push (corrections and multi-step pushes count)
    hand: Hand
    arm: Arm
    object: ObjectRef  # the library object, mesh or captured point cloud (reconstructed by whoever draws it)
    frame: DirectionFrame  # where the object is at the push's start and which way it is pushed
    distance_m: PositiveFloat | None = None  # how far it should go (None when unknown: a random choice)
    obstacles: list[Obstacle] = Field(default_factory=list)
    candidates_world: PoseArray
    critic_scores: FloatVector | None = None
    rollouts: list[RolloutPreview] = Field(default_factory=list)
    chosen: int | None = Field(default=None, ge=0)
    plan: Plan

    @model_validator(mode="after")
    def _consistent(self) -> PushDecision:
        _check_pair(self.hand, self.arm)
        _require_rows("PushDecision", _rows(self.candidates_world), critic_scores=self.critic_scores)
        if self.chosen is not None and self.chosen >= len(self.rollouts):
            raise ValueError(f"PushDecision: chosen {self.chosen} but {len(self.rollouts)} rollouts")
        return self

"""Coverage of a pose source over objects: how many sampled poses push, and does any push at all.

The shared measurement behind the data-size experiment (paper Table "objects with >= 1 feasible
pose") and the sampler-quality benchmark. For every object:

1. the object rests in its default pose at the origin and is pushed along +x (`default_frame`), so
   D = world; with `yaw="random"` it is first turned about z by a yaw drawn from (settings seed,
   object id) alone, as an object placed by a user would be (the version-1 data only ever saw yaw 0);
2. the pose source draws `samples` poses (200, the paper's count) for it in D, seeded from
   (settings seed, object id) so a record never depends on scheduling or on other objects;
3. the poses are pushed in order in the floating-hand validator — the data engine's success criterion
   (centre within 0.03 m of the goal, <= 45 deg turned) — in its nominal physics (`world="exact"`), or
   with `world="real"` in an execution world drawn per object that the pose source does not know
   (shared/world/sim/world.py: friction, rolling friction, mass, centre of mass, and where the object
   truly stands; the arm's controller draws do not apply to the floating hand). The source is then
   told the mesh at a pose off by the world's error (`cameras=0`) or, with `cameras` 1-3, gets only
   what that many simulated depth cameras see of the object standing at the evaluation's spot: it
   samples for the reconstruction, in the direction frame of the reconstruction's pose, as the
   sampler service does for a point cloud (`Sighting`). Every source of a run sees the same world and
   the same capture of an object (both drawn from the settings seed and the object id), so their
   outcomes pair up object by object:
   - the first `fraction_poses` (50) are all pushed: successes / pushed = `validated_fraction`;
   - then chunks of `chunk` (25) are pushed only until one pose has succeeded or all are tried:
     `any_success` ("the object has >= 1 validated pose of 200").

Early stopping is exact for `any_success`: the poses are drawn before any is pushed, each push
starts from the same restored scene (outcomes do not depend on what ran before), and the question
is only whether *some* pose succeeds, so stopping at the first success gives the count that pushing
all 200 would. It saves most of the cost: an object with a success among its first 50 poses costs
50 pushes instead of 200, and only the objects with no validated pose at all cost the full 200. `n_success` is
therefore a lower bound beyond the first `fraction_poses`; the rates reported use the first
`fraction_poses` only, which every object has pushed in full.

Objects are spread over `workers` spawn processes (one PyBullet scene and one torch thread each);
every finished object is one record in a `ResultStore`, so a killed run resumes where it stopped.
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import multiprocessing
import multiprocessing.pool
import os
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, cast

import numpy as np
from tqdm import tqdm

from evaluation.report import CODE_AT_START
from evaluation.store import ResultStore

SAMPLES_PER_OBJECT = 200  # the paper's candidates per test object
FRACTION_POSES = 50  # poses always pushed: the validated-fraction estimate
CHUNK_POSES = 25  # then pushed this many at a time until one succeeds

HAND = "allegro"  # the hand the coverage experiments measure (the shipped Allegro checkpoint and dataset)
DEFAULT_DATASET = Path(__file__).resolve().parents[1] / "data" / f"{HAND}-train"
TARGET_COVERED_PCT = 75.0  # target: test objects with >= 1 validated pose of 200 samples
COVERAGE_YAWS = ("zero", "random")
COVERAGE_WORLDS = ("exact", "real")
NOT_PERCEIVED = "not perceived"  # a failure kind of the camera runs: the capture could not be reconstructed


class CoverageError(ValueError):
    """Settings or a pose source the measurement cannot use."""


# ----------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class CoverageSettings:
    """What fixes a coverage record (pinned in the experiment's store)."""

    samples: int = SAMPLES_PER_OBJECT
    fraction_poses: int = FRACTION_POSES
    chunk: int = CHUNK_POSES
    seed: int = 0
    hand: str = HAND
    yaw: str = "zero"  # "zero": yaw 0 in D (the paper's protocol); "random": a seeded yaw per object
    world: str = "exact"  # "exact": the validator's nominal physics; "real": a drawn execution world per object
    cameras: int = 0  # 0: the source is told the mesh; 1-3: it gets that many depth cameras' view of the object

    def __post_init__(self) -> None:
        if self.yaw not in COVERAGE_YAWS:
            raise CoverageError(f"yaw must be one of {', '.join(COVERAGE_YAWS)}, got {self.yaw!r}")
        if self.world not in COVERAGE_WORLDS:
            raise CoverageError(f"world must be one of {', '.join(COVERAGE_WORLDS)}, got {self.world!r}")
        if self.cameras not in (0, 1, 2, 3):
            raise CoverageError(f"cameras must be 0 (the mesh is told) or 1-3, got {self.cameras}")
        if self.samples < 1 or self.fraction_poses < 1 or self.chunk < 1:
            raise CoverageError(f"samples, fraction_poses and chunk must be >= 1; got {self.samples}, "
                                f"{self.fraction_poses}, {self.chunk}")
        if self.fraction_poses > self.samples:
            raise CoverageError(f"fraction_poses ({self.fraction_poses}) cannot exceed samples ({self.samples})")

    def to_dict(self) -> dict[str, Any]:
        settings = dataclasses.asdict(self)
        # the pin of the stores made before these settings existed
        for name, first in (("yaw", "zero"), ("world", "exact"), ("cameras", 0)):
            if settings[name] == first:
                del settings[name]
        return settings

    @property
    def perceived(self) -> bool:
        """True when the measurement differs from the first protocol: a drawn world or a camera's view."""
        return self.world != "exact" or self.cameras > 0

    @property
    def world_suffix(self) -> str:
        """What a results directory's name says of the world: `-<world>[-cameraN]`, nothing for the exact world
        told the mesh (the names of the runs made before worlds existed)."""
        if not self.perceived:
            return ""
        return f"-{self.world}" + (f"-camera{self.cameras}" if self.cameras else "")


def object_seed(seed: int, object_id: str, purpose: str = "") -> int:
    """The sampling seed of one object: from (settings seed, object id) only, never from scheduling."""
    digest = hashlib.sha256(f"gd2p-coverage:{seed}:{object_id}{purpose}".encode()).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


def object_yaw_rad(settings: CoverageSettings, object_id: str) -> float:
    """The object's yaw in D: 0, or with `yaw="random"` uniform in [-pi, pi) from (seed, object id)."""
    if settings.yaw == "zero":
        return 0.0
    return float(np.random.default_rng(object_seed(settings.seed, object_id, ":yaw")).uniform(-math.pi, math.pi))


def coverage_frame(obj: Any, settings: CoverageSettings, object_id: str) -> Any:
    """The frame an object is measured in: default resting pose at the origin, turned, pushed along +x."""
    from shared.contracts.messages import DirectionFrame
    from shared.sampling.sampling import default_frame
    from shared.world.push_outcome import object_pose

    yaw = object_yaw_rad(settings, object_id)
    if yaw == 0.0:
        return default_frame(obj)
    return DirectionFrame(object_pose=object_pose(obj.T_D_O(None, yaw)), yaw_deg=0.0)


# ----------------------------------------------------------------------------- pose sources
class PoseSource(Protocol):
    """Draws candidate poses in D for an object placed by a frame. Picklable (sent to workers)."""

    def label(self) -> str: ...

    def poses(self, obj: Any, frame: Any, k: int, seed: int) -> np.ndarray:
        """[<= k, 25] poses in D."""
        ...


_OPEN_SOURCES: OrderedDict[tuple, Any] = OrderedDict()  # per process: loaded checkpoints / indexes
_OPEN_LIMIT = 3  # a critic-ordered retrieval holds an index, a sampler (its BPS encoder) and a critic


def _cached(key: tuple, load: Callable[[], Any], close: Callable[[Any], None] | None = None) -> Any:
    if key in _OPEN_SOURCES:
        _OPEN_SOURCES.move_to_end(key)
        return _OPEN_SOURCES[key]
    value = load()
    _OPEN_SOURCES[key] = value
    while len(_OPEN_SOURCES) > _OPEN_LIMIT:
        _, evicted = _OPEN_SOURCES.popitem(last=False)
        if hasattr(evicted, "close"):
            evicted.close()
    return value


@dataclass(frozen=True)
class DiffusionSource:
    """Poses from a sampler checkpoint (`PoseSampler.sample`), DDPM or DDIM; with `critic` and `guidance`, the
    last denoising steps steered up the critic's log P(success) (`shared.sampling.guidance`)."""

    checkpoint: str
    sampler: str = "ddpm"
    steps: int | None = None  # None: the sampler's default (DDPM 100, DDIM 10)
    noise_scale: float | None = None  # the sampling temperature (sample_normalized); None: the sampler's default
    critic: str | None = None  # a `gd2p critic train` checkpoint trained for `checkpoint`, guiding the samples
    guidance: Any = None  # its `GradientGuidance`

    def label(self) -> str:
        steps = self.steps if self.steps is not None else (100 if self.sampler == "ddpm" else 10)
        temperature = "" if self.noise_scale in (None, 1.0) else f", noise x{self.noise_scale:g}"
        guided = "" if self.guidance is None else f", critic-guided ({guidance_text(self.guidance)})"
        return f"{self.sampler.upper()}-{steps}{temperature}{guided}"

    def pose_sampler(self) -> Any:
        """The checkpoint's `PoseSampler`, loaded once per process."""
        from shared.sampling.sampling import PoseSampler

        return _cached(("diffusion", self.checkpoint, _file_stamp(self.checkpoint)), lambda: PoseSampler(self.checkpoint))

    def poses(self, obj: Any, frame: Any, k: int, seed: int) -> np.ndarray:
        critic = None if self.critic is None else critic_for(self.critic, self.checkpoint).model
        return self.pose_sampler().sample(obj, frame, k=k, sampler=self.sampler, steps=self.steps, seed=seed,
                                          noise_scale=self.noise_scale, critic=critic, guidance=self.guidance).poses_d


def guidance_text(guidance: Any) -> str:
    """'step x0.02, last 10 steps, <= 0.2' for a GradientGuidance."""
    return f"step x{guidance.scale:g}, last {guidance.steps} steps, <= {guidance.max_step:g}"


def critic_for(critic: str, checkpoint: str) -> Any:
    """The critic (`LoadedCritic`) at `critic`, loaded once per process; CoverageError for a critic trained for
    another sampler checkpoint than `checkpoint` (it encodes objects with that checkpoint's BPS)."""
    from shared.sampling.checkpoint import checkpoint_id
    from shared.sampling.critic_train import load_critic

    def load() -> Any:
        loaded = load_critic(critic)
        if loaded.sampler_checkpoint_id != checkpoint_id(checkpoint):
            raise CoverageError(f"the critic {critic} was trained for the sampler checkpoint "
                                f"{loaded.sampler_checkpoint_id}, not {checkpoint} ({checkpoint_id(checkpoint)})")
        return loaded

    return _cached(("critic", critic, _file_stamp(critic), checkpoint), load)


@dataclass(frozen=True)
class NearestNeighborSource:
    """The paper's Nearest Neighbor baseline: the stored poses of the training frame nearest in BPS.

    A frame holds fewer poses than 200 (typically 20-90), so this source gives all of them — fewer
    candidates than the model's 200; the per-object record says how many.
    """

    index: str  # a NearestNeighborBaseline .npz
    fill: bool = False  # the nearest frames' poses up to k, so retrieval gets the model's candidate budget

    def label(self) -> str:
        return "Nearest neighbour, nearest frames up to K" if self.fill else "Nearest neighbour"

    def sampler(self) -> Any:
        """The index served as the sampler service serves it (`NearestNeighborSampler`), loaded once per process."""
        from shared.sampling.nearest_neighbor import NearestNeighborSampler

        return _cached(("nn", self.index, _file_stamp(self.index)), lambda: NearestNeighborSampler.load(self.index))

    def poses(self, obj: Any, frame: Any, k: int, seed: int) -> np.ndarray:
        sampler = self.sampler()
        if self.fill:
            points_d, _, _ = sampler.points_in_d(obj, frame)
            return sampler.index.nearest_frames_poses(sampler.index.bps.encode(points_d), k)
        return sampler.sample(obj, frame, k=k, seed=seed).result.poses_d


@dataclass(frozen=True)
class CriticOrderedSource:
    """Another source's poses, most likely to push well first by the success critic: the order the planner's
    critic path (`PlannerOptions.critic`) tries them in, so the first poses pushed are the ones it would plan.

    The critic scores a pose from the object's BPS as `checkpoint`'s sampler encodes it (the encoding it was
    trained on), whatever the poses came from.
    """

    inner: DiffusionSource | NearestNeighborSource | CriticClimbedSource
    checkpoint: str  # the sampler checkpoint the critic was trained for
    critic: str  # a `gd2p critic train` checkpoint

    def label(self) -> str:
        return f"{self.inner.label()}, critic order"

    def scorer(self) -> Any:
        """The critic (`LoadedCritic`), loaded once per process; CoverageError for a critic of another checkpoint."""
        return critic_for(self.critic, self.checkpoint)

    def poses(self, obj: Any, frame: Any, k: int, seed: int) -> np.ndarray:
        from shared.sampling.critic_train import success_probabilities_for

        poses = self.inner.poses(obj, frame, k, seed)
        critic = self.scorer()
        scores = success_probabilities_for(critic.model, critic.hand, DiffusionSource(self.checkpoint).pose_sampler(),
                                           obj, frame, poses)
        return poses[np.argsort(-scores, kind="stable")]


@dataclass(frozen=True)
class CriticClimbedSource:
    """Another source's poses moved up the critic's log P(success) as critic-guided sampling moves the model's:
    `guidance.steps` steps of the same size and cap in the sampler's normalised pose space, without denoising
    between them (retrieval has no reverse process). Retrieval's counterpart of guided sampling, so the two
    compare with the same critic and the same number of its gradients."""

    inner: NearestNeighborSource
    checkpoint: str  # the sampler checkpoint whose normalisation and BPS the critic was trained with
    critic: str
    guidance: Any  # a `GradientGuidance`

    def label(self) -> str:
        return f"{self.inner.label()}, climbed the critic ({guidance_text(self.guidance)})"

    def poses(self, obj: Any, frame: Any, k: int, seed: int) -> np.ndarray:
        import torch

        from shared.robots.hands import load_hand
        from shared.sampling.guidance import CriticGuide

        poses = self.inner.poses(obj, frame, k, seed)
        sampler = DiffusionSource(self.checkpoint).pose_sampler()
        points_d, _, label = sampler.points_in_d(obj, frame)
        critic = critic_for(self.critic, self.checkpoint)
        guide = CriticGuide(critic.model, load_hand(critic.hand), sampler.encode_points(points_d, label), points_d,
                            sampler.normalizer)
        normalized = sampler.normalizer.normalize(torch.as_tensor(poses, dtype=torch.float32)).clamp(-1.0, 1.0)
        for _ in range(self.guidance.steps):
            normalized = self.guidance.move(normalized, guide)
        return sampler.clean_poses(normalized)


def _file_stamp(path: str) -> tuple[int, int]:
    stat = Path(path).stat()
    return stat.st_size, stat.st_mtime_ns


# ----------------------------------------------------------------------------- early stopping
@dataclass
class PushTally:
    """Outcomes of one object's poses as far as they were pushed."""

    n_poses: int
    successes: list[bool]
    fraction_poses: int

    @property
    def n_validated(self) -> int:
        return len(self.successes)

    @property
    def first_success_index(self) -> int | None:
        return self.successes.index(True) if True in self.successes else None

    @property
    def fraction_pushed(self) -> int:
        return min(self.fraction_poses, self.n_poses)

    @property
    def fraction_successes(self) -> int:
        return sum(self.successes[: self.fraction_poses])

    @property
    def validated_fraction(self) -> float:
        return self.fraction_successes / self.fraction_pushed if self.fraction_pushed else 0.0


def push_until_covered(n_poses: int, push: Callable[[int, int], Sequence[bool]], fraction_poses: int = FRACTION_POSES,
                       chunk: int = CHUNK_POSES) -> PushTally:
    """Push poses [0, fraction_poses) all, then chunks of `chunk` until one succeeded or all are pushed.

    `push(start, stop)` pushes poses start..stop-1 and returns their successes.
    """
    successes: list[bool] = []
    stop = min(fraction_poses, n_poses)
    while True:
        start = len(successes)
        if stop > start:
            outcome = [bool(s) for s in push(start, stop)]
            if len(outcome) != stop - start:
                raise CoverageError(f"push({start}, {stop}) returned {len(outcome)} outcomes")
            successes += outcome
        if any(successes) or len(successes) >= n_poses:
            return PushTally(n_poses, successes, fraction_poses)
        stop = min(len(successes) + chunk, n_poses)


# ----------------------------------------------------------------------------- one object
_WORKER_STATE: dict[str, Any] = {}


def _validator():
    from shared.validation.validator import Validator

    if "validator" not in _WORKER_STATE:
        _WORKER_STATE["validator"] = Validator()  # default physics: the data engine's criterion
    return _WORKER_STATE["validator"]


def _hand(name: str):
    from shared.robots.hands import load_hand

    hands = _WORKER_STATE.setdefault("hands", {})
    if name not in hands:
        hands[name] = load_hand(name)
    return hands[name]


# ----------------------------------------------------------------------------- what the source is given
@dataclass(eq=False)
class Sighting:
    """What a pose source is given of an object, and how its poses map onto the true object.

    `sampler_input` is what `PoseSampler.sample` takes: the told `ObjectModel`, or a capture's object points
    in the world (thinned as the sampler service thins a request's cloud); `frame` places it (its pose as
    told or as reconstructed, pushed along +x); `T_true_seen` is the source's direction frame D in the
    measurement's coordinates (the validator's scene, where the true object stands at `coverage_frame`);
    a told pose error moves the true object instead (`object_offset`)."""

    sampler_input: Any
    frame: Any
    T_true_seen: np.ndarray
    object_offset: np.ndarray | None = None  # 4x4 in D: where the true object stands relative to the told pose


def coverage_world(obj: Any, settings: CoverageSettings, object_id: str) -> Any:
    """The object's execution world (`sample_world`), drawn around the validator's nominal physics from
    (settings seed, object id): the same for every source measured, so sources pair up object by object."""
    from shared.world.sim.params import PhysicsParams
    from shared.world.sim.world import WorldLevel, half_extents, sample_world

    level = cast(WorldLevel, settings.world)  # one of COVERAGE_WORLDS: __post_init__ checks it
    return sample_world(level, object_seed(settings.seed, object_id, ":world"), half_extents(obj.mesh.vertices),
                        base=PhysicsParams(), cameras=settings.cameras)


def sight(obj: Any, frame: Any, world: Any) -> Sighting:
    """What the pose source gets of `obj` standing at `frame` in `world`; ObjectLoadError when the cameras'
    view cannot be reconstructed."""
    from shared.frames import frame_object_transform, frame_transform

    if not world.cameras:
        T_told = frame_object_transform(frame)
        offset = world.pose_error.true_pose(T_told) @ np.linalg.inv(T_told)
        return Sighting(obj, frame, frame_transform(frame), None if np.allclose(offset, np.eye(4)) else offset)
    return _camera_sighting(obj, frame, world)


def _camera_sighting(obj: Any, frame: Any, world: Any) -> Sighting:
    """The object captured by `world.cameras` cameras where the evaluation stands objects (so the cameras look
    at it from the evaluation's angles), reconstructed, and carried back to the measurement's coordinates."""
    from evaluation.push_protocol import OBJECT_XY
    from shared.contracts.messages import DirectionFrame, ObjectRef
    from shared.frames import frame_object_transform, frame_transform, make_transform
    from shared.world.object_refs import captured_object
    from shared.world.perception import bps_points, cloud_for_request
    from shared.world.push_outcome import object_pose
    from shared.world.sim.camera import capture_object

    spot = np.array([OBJECT_XY[0], OBJECT_XY[1], 0.0])
    capture = capture_object(obj, make_transform(np.eye(3), spot) @ frame_object_transform(frame),
                             n_cameras=world.cameras, seed=world.seed)
    captured = captured_object(ObjectRef(point_cloud=cloud_for_request(capture.cloud)))  # as a request's cloud is
    T_seen = captured.T_world_O.copy()
    T_seen[:3, 3] -= spot
    seen = DirectionFrame(object_pose=object_pose(T_seen), yaw_deg=frame.yaw_deg)
    return Sighting(bps_points(captured.object_points) - spot, seen, frame_transform(seen))


def measure_object(source: PoseSource, object_id: str, settings: CoverageSettings) -> dict[str, Any]:
    """Sample, push with early stopping, and return the object's coverage record."""
    from shared.frames import object_yaw_in_d, poses_d_to_world
    from shared.validation.push import table_object
    from shared.world.objects import ObjectLoadError, load_object

    started = time.perf_counter()
    obj = load_object(object_id)
    frame = coverage_frame(obj, settings, object_id)
    world = coverage_world(obj, settings, object_id)
    try:
        seen = sight(obj, frame, world)
    except ObjectLoadError as exc:
        return not_perceived_record(object_id, settings, world, str(exc), time.perf_counter() - started)
    poses_seen = source.poses(seen.sampler_input, seen.frame, settings.samples, object_seed(settings.seed, object_id))
    poses = poses_d_to_world(np.asarray(poses_seen, dtype=np.float64), seen.T_true_seen)  # into the true D
    placed = table_object(obj, None, object_yaw_in_d(frame, obj.default_pose.rotation), world.mass_scale, world.com_offset_m)
    validator, hand = _validator(), _hand(settings.hand)
    params = world.physics if settings.world == "real" else None  # exact: the validator's own (the first protocol)
    failures: list[str | None] = []

    def push(start: int, stop: int) -> list[bool]:
        outcomes = validator.validate(placed, hand, poses[start:stop], params=params,
                                      object_offsets=[seen.object_offset] * (stop - start)).outcomes
        failures.extend(o.failure() for o in outcomes)
        return [o.success for o in outcomes]

    tally = push_until_covered(len(poses), push, settings.fraction_poses, settings.chunk)
    record = coverage_record(object_id, tally, time.perf_counter() - started, validated_spread_cm(poses, tally))
    record["failures"] = failure_counts(failures[: tally.fraction_pushed], settings)
    if settings.perceived:
        record["world"] = world.record()
    return record


def not_perceived_record(object_id: str, settings: CoverageSettings, world: Any, why: str, seconds: float) -> dict[str, Any]:
    """An object the cameras' view could not be reconstructed from: no pose pushed, every one of its
    `fraction_poses` counted as failed (the planner would have had nothing to push either)."""
    tally = PushTally(settings.fraction_poses, [False] * settings.fraction_poses, settings.fraction_poses)
    record = coverage_record(object_id, tally, seconds)
    record.update(n_poses=0, n_validated=0, not_perceived=why, world=world.record(),
                  failures={**failure_counts([], settings), NOT_PERCEIVED: settings.fraction_poses})
    return record


def failure_counts(failures: Sequence[str | None], settings: CoverageSettings | None = None) -> dict[str, int]:
    """How many of the pushes failed in each way (`PushOutcome.failure`), every kind listed (with cameras
    also the poses lost to a capture that could not be reconstructed)."""
    from shared.validation.push import FAILURES

    kinds = [*FAILURES, NOT_PERCEIVED] if settings is not None and settings.cameras else list(FAILURES)
    return {kind: sum(f == kind for f in failures) for kind in kinds}


def validated_spread_cm(poses: np.ndarray, tally: PushTally) -> float | None:
    """How far apart the validated poses among the first `fraction_poses` are: the RMS distance (cm) of their
    palm positions from their mean. A source that repeats one good pose scores high validated fractions
    with a spread near 0; None with fewer than two validated poses."""
    pushed = np.asarray(tally.successes[: tally.fraction_pushed], dtype=bool)
    positions = poses[: len(pushed)][pushed, :3]
    if len(positions) < 2:
        return None
    return round(100.0 * float(np.sqrt(((positions - positions.mean(axis=0)) ** 2).sum(axis=1).mean())), 3)


def coverage_record(object_id: str, tally: PushTally, seconds: float, spread_cm: float | None = None) -> dict[str, Any]:
    return {
        "object": object_id,
        "n_poses": tally.n_poses,
        "n_validated": tally.n_validated,
        "n_success": sum(tally.successes),
        "fraction_pushed": tally.fraction_pushed,
        "fraction_successes": tally.fraction_successes,
        "validated_fraction": tally.validated_fraction,
        "any_success": tally.first_success_index is not None,
        "first_success_index": tally.first_success_index,
        "validated_spread_cm": spread_cm,
        "seconds": round(seconds, 3),
        "code": CODE_AT_START,
    }


# ----------------------------------------------------------------------------- workers
def _init_worker() -> None:
    import torch

    torch.set_num_threads(1)  # one busy process per core (docs/architecture.md §Compute)
    os.dup2(2, 1)  # PyBullet prints on fd 1; keep the parent's stdout clean


def _measure_task(task: tuple[str, PoseSource, str, CoverageSettings]) -> tuple[str, dict[str, Any]]:
    key, source, object_id, settings = task
    try:
        return key, measure_object(source, object_id, settings)
    except Exception as exc:  # name the object: a worker's traceback does not reach the parent
        raise CoverageError(f"{source.label()} on {object_id}: {type(exc).__name__}: {exc}") from exc


class CoveragePool:
    """Spawn worker processes measuring objects; one pool can serve several sources in turn.

    With `workers <= 1` the objects are measured in the calling process (no start-up cost).
    """

    def __init__(self, workers: int = 2):
        self.workers = max(1, int(workers))
        self._pool: multiprocessing.pool.Pool | None = None

    def __enter__(self) -> CoveragePool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
            self._pool = None

    def _results(self, tasks: list[tuple[str, PoseSource, str, CoverageSettings]]) -> Iterator[tuple[str, dict[str, Any]]]:
        if self.workers == 1:
            for task in tasks:
                yield _measure_task(task)
            return
        if self._pool is None:
            self._pool = multiprocessing.get_context("spawn").Pool(self.workers, initializer=_init_worker)
        yield from self._pool.imap_unordered(_measure_task, tasks, chunksize=1)

    def measure(self, source: PoseSource, object_ids: Sequence[str], store: ResultStore, key_prefix: str,
                settings: CoverageSettings, desc: str | None = None, progress: bool = True) -> list[dict[str, Any]]:
        """Coverage records of `object_ids` (in that order); objects already in `store` are not redone."""
        keys = {object_id: f"{key_prefix}/{object_id}" for object_id in object_ids}
        pending = [(keys[o], source, o, settings) for o in object_ids if not store.done(keys[o])]
        done = [store.records[keys[o]] for o in object_ids if store.done(keys[o])]
        with tqdm(total=len(object_ids), initial=len(done), desc=desc or source.label(), unit="obj",
                  disable=not progress, dynamic_ncols=True) as bar:
            bar.set_postfix(live_postfix(done), refresh=False)
            for key, record in self._results(pending):
                store.add(key, record)
                done.append(store.records[key])
                bar.set_postfix(live_postfix(done), refresh=False)
                bar.update(1)
        return [store.records[keys[o]] for o in object_ids]


def measure_coverage(source: PoseSource, object_ids: Sequence[str], store: ResultStore, key_prefix: str,
                     settings: CoverageSettings | None = None, workers: int = 2, desc: str | None = None,
                     progress: bool = True) -> list[dict[str, Any]]:
    """One source over `object_ids` with a fresh pool (see `CoveragePool.measure`)."""
    with CoveragePool(workers) as pool:
        return pool.measure(source, object_ids, store, key_prefix, settings or CoverageSettings(), desc, progress)


# ----------------------------------------------------------------------------- summaries
def pose_trials(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Each pose of the records' validated-fraction window as one trial `{"object_id", "success"}`.

    What `evaluation.stats` bootstraps: the pooled validated fraction with its interval clustered by
    object (`success_interval`), or a paired difference between two sources (`difference_interval`).
    """
    return [{"object_id": r["object"], "success": i < r["fraction_successes"]}
            for r in records for i in range(r["fraction_pushed"])]


def live_postfix(records: Sequence[Mapping[str, Any]]) -> dict[str, str]:
    """Progress-bar figures so far: objects covered and the pooled validated fraction."""
    if not records:
        return {}
    summary = summarize(records)
    return {"covered": f"{summary['covered']}/{summary['objects']}", "valid": f"{summary['pooled_validated_fraction']:.0%}"}


def summarize(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Objects, objects covered (>= 1 validated pose), mean / pooled validated fraction, pushes, seconds."""
    n = len(records)
    pushed = sum(r["fraction_pushed"] for r in records)
    spreads = [r["validated_spread_cm"] for r in records if r.get("validated_spread_cm") is not None]
    return {
        "objects": n,
        "covered": sum(bool(r["any_success"]) for r in records),
        "covered_pct": 100.0 * sum(bool(r["any_success"]) for r in records) / n if n else math.nan,
        "mean_validated_fraction": float(np.mean([r["validated_fraction"] for r in records])) if n else math.nan,
        "pooled_validated_fraction": sum(r["fraction_successes"] for r in records) / pushed if pushed else math.nan,
        "pushes": sum(r["n_validated"] for r in records),
        # None for stores made before the spread was recorded
        "median_validated_spread_cm": float(np.median(spreads)) if spreads else None,
        "seconds": round(sum(r["seconds"] for r in records), 1),
        # Shares of the pushed poses (the first `fraction_poses` of each object) that failed each way; None for
        # stores made before failures were recorded.
        "failure_shares": _failure_shares(records, pushed),
    }


def _failure_shares(records: Sequence[Mapping[str, Any]], pushed: int) -> dict[str, float] | None:
    if not pushed or any("failures" not in r for r in records):
        return None
    kinds = records[0]["failures"].keys()
    return {kind: sum(r["failures"][kind] for r in records) / pushed for kind in kinds}


# ----------------------------------------------------------------------------- the world beside exact
def world_text(settings: CoverageSettings) -> str:
    """One sentence on the world the poses were pushed in and what the sources were given."""
    if not settings.perceived:
        return "the validator's nominal physics, the source told the object's mesh and exact pose"
    physics = ("an execution world drawn per object that the source does not know (friction, rolling friction, mass, "
               "centre of mass drawn from the `real` ranges of shared/world/sim/world.py; the floating hand has no arm "
               "controller to draw)" if settings.world == "real" else "the validator's nominal physics")
    given = (f"the source given only what {settings.cameras} simulated depth camera{'s' if settings.cameras > 1 else ''} "
             "see of the object (it samples for its own reconstruction, in the direction frame of the reconstruction's "
             "pose; a capture that cannot be reconstructed fails all its poses)" if settings.cameras else
             "the source told the mesh at a pose off by the world's ±1 cm / ±5° error")
    return f"{physics}, {given}"


def world_rows(perceived: Mapping[str, Sequence[Mapping[str, Any]]],
               exact: Mapping[str, Sequence[Mapping[str, Any]]]) -> list[dict[str, Any]]:
    """Per source measured in both worlds, on the objects both measured: the validated fraction and objects covered
    in each, and the perceived world's minus the exact world's validated fraction, paired by object."""
    from evaluation.stats import difference_interval, success_interval

    rows = []
    for label, records in perceived.items():
        if not exact.get(label):
            continue
        objects = {r["object"] for r in records} & {r["object"] for r in exact[label]}
        mine = [r for r in records if r["object"] in objects]
        theirs = [r for r in exact[label] if r["object"] in objects]
        rows.append({"source": label, "objects": len(objects),
                     "exact": success_interval(pose_trials(theirs)).as_dict(), "perceived": success_interval(pose_trials(mine)).as_dict(),
                     "difference": difference_interval(pose_trials(mine), pose_trials(theirs)).as_dict(),
                     "covered_exact": summarize(theirs)["covered"], "covered_perceived": summarize(mine)["covered"]})
    return rows


def world_markdown(rows: Sequence[Mapping[str, Any]], settings: CoverageSettings, exact_from: str) -> str:
    """`world_rows` as a table with a line on where the exact figures come from (empty without rows)."""
    from evaluation.report import markdown_table

    if not rows:
        return ""

    def cell(v: Mapping[str, float]) -> str:
        return f"{v['value']:.1%} [{v['low']:.1%}, {v['high']:.1%}]"

    label = f"{settings.world}{f', {settings.cameras} cameras' if settings.cameras else ', mesh told'}"
    table = markdown_table(
        ["source", "objects", "validated fraction, exact", f"validated fraction, {label}", f"{settings.world} − exact (points, paired by object)",
         "covered, exact", f"covered, {settings.world}"],
        [[r["source"], r["objects"], cell(r["exact"]), cell(r["perceived"]),
          f"{100 * r['difference']['value']:+.1f} [{100 * r['difference']['low']:+.1f}, {100 * r['difference']['high']:+.1f}]",
          r["covered_exact"], r["covered_perceived"]] for r in rows])
    return (f"\n### Beside the `exact` world\n\nThe same sources on the same objects in the `exact` world ({exact_from}) "
            f"beside this run's, 95% intervals clustered by object:\n\n{table}\n")

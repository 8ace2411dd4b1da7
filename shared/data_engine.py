"""The data engine: objects -> generator -> validator (+ Halton augmentation) -> pose store.

A client of the generator and validator services over the bus (two `Dispatcher`s); it never calls
their algorithms directly, so the same build runs on one laptop or on a farm of workers joined to
one router. For each object, in a fixed order:

    round r = 0, 1, ...:
        placement r = (resting pose, yaw) = f(seed, object, r, "placement")        (below)
        GenerationJob(object, hand, placement r, batch_size = per_object, seed = f(seed, object, r, "generate"))
        ValidationJob(the candidates, placement r, augment=True, seed = f(seed, object, r, "validate"))
        keep every candidate and every augmented copy with its outcome (successes and failures)
    while r + 1 < min_rounds, or the object has fewer than `min_poses` successful poses,
    up to `max_rounds` rounds
    store.write_object(...)   # one atomic shard + manifest update per object

Placements (dataset v2, `placement="random"`, the default). Each round is one generation job with a
placement of its own: a yaw uniform in [-180, 180) degrees about D's z, and a resting pose - round 0
the object's default resting pose (the one the planner's floating-hand pre-screen and every
evaluation put it in, so every object has poses for the placement it is tested in), each later
round a resting pose drawn with probability proportional to its stability (trimesh's quasi-static
drop probability, floored at 1% so a native pose that drops rarely still comes up). Why drawn and
not one round per resting pose: most library objects keep 6-9 resting poses, many of them the same
lying pose at another roll (a capsule's side is 7 hull facets of 6% each, a cylinder's 6 of 2%), so
a round for each would multiply the build's cost by ~8 and spend most of it on near-duplicate and
unlikely poses; drawn by stability, the dataset covers the poses as often as objects are found in
them, and every round - the unit of cost - adds a new yaw, which is what the version-1 data lacked
(every frame at yaw 0). `min_rounds` sets how many placements every object gets. The generator and
the validator place the object alike: the GenerationJob carries `pose_index` and `yaw_rad`, the
ValidationJob the same `pose_index` and a `frame` whose object is that pose turned by that yaw (the
validator's existing floating-hand placement path). `placement="default"` is version 1's placement
(default resting pose, yaw 0).

Every seed, placements included, is derived from (build seed, object id, round, purpose), never
from scheduling, and both services are deterministic for a seed, so an object's rows do not depend
on which worker ran it, on how many objects were in flight, or on whether the build was interrupted
and resumed: a resumed build skips the objects the manifest marks done and ends with the same rows
as an uninterrupted one.

Failures are kept: every raw candidate is stored with its outcome, and every Halton copy (the
validator copies successes only). `DatasetStore.rows()` gives the successes unless asked otherwise,
so training and the other readers see what they saw before.

Several objects are in flight at once (one more generation job than there are generator workers,
and every finished generation goes straight to the validators), so every worker stays busy.
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import platform
import subprocess
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import asdict, dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from shared.bus import Dispatcher, DispatchError
from shared.contracts.messages import (
    DirectionFrame,
    ErrorReply,
    GenerationJob,
    GenerationResult,
    Message,
    ObjectRef,
    PhysicsSettings,
    ValidationJob,
    ValidationResult,
)
from shared.data.dataset_store import COUNT_KEYS, DatasetStore
from shared.world.objects import (
    ObjectLoadError,
    ObjectModel,
    library_generation,
    list_object_ids,
    load_object,
    split_of,
)
from shared.world.objects.final_split import is_final_id
from shared.world.objects.geometry import MIN_POSE_PROBABILITY
from shared.world.push_outcome import TOPPLED_TILT_DEG, object_pose
from shared.world.sim import PhysicsParams

TRAINING_SPLIT = "train"
ENERGY_TERMS = ("fc", "dis", "pen", "spen", "joints", "ff", "fp", "tpen", "dir", "arm", "total")
OUTCOME_COLUMNS = ("success", "position_error_m", "rotation_deg", "max_tilt_deg", "contact_kept", "hand_table_contact",
                   "initial_penetration_m")
PLACEMENTS = ("random", "default")  # BuildSettings.placement: dataset v2's random yaws and resting poses | version 1's


class BuildError(RuntimeError):
    """A build that cannot start or go on (bad selection, split violation, workers unreachable)."""


# ----------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class BuildSettings:
    """What fixes a dataset's content (recorded in the manifest; a resume must match it)."""

    hand: str
    split: str = TRAINING_SPLIT
    per_object: int = 32  # generator candidates per object and round
    seed: int = 0
    iterations: int | None = None  # generator iterations; None = the generator's default
    min_poses: int = 0  # run more rounds while an object has fewer successful poses than this ...
    min_rounds: int = 1  # ... or has had fewer rounds (placements) than this ...
    max_rounds: int = 1  # ... up to this many rounds
    placement: str = "random"  # "random": a random yaw and a drawn resting pose per round; "default": yaw 0, default pose
    push_distance_m: float = 0.20
    physics: dict[str, Any] = field(default_factory=lambda: default_physics().model_dump())

    def __post_init__(self) -> None:
        if self.per_object < 1:
            raise BuildError(f"--per-object must be >= 1, got {self.per_object}")
        if self.max_rounds < 1:
            raise BuildError(f"--max-rounds must be >= 1, got {self.max_rounds}")
        if not 1 <= self.min_rounds <= self.max_rounds:
            raise BuildError(f"--min-rounds must be between 1 and --max-rounds ({self.max_rounds}), got {self.min_rounds}")
        if self.min_poses < 0:
            raise BuildError(f"--min-poses must be >= 0, got {self.min_poses}")
        if self.placement not in PLACEMENTS:
            raise BuildError(f"--placement must be one of {', '.join(PLACEMENTS)}, got {self.placement!r}")

    def parameters(self) -> dict[str, Any]:
        return asdict(self)


def default_physics() -> PhysicsSettings:
    """The validator's measured default solver settings, sent explicitly so the manifest names them."""
    params = PhysicsParams()
    return PhysicsSettings(solver_iterations=params.solver_iterations, time_step_s=params.time_step_s,
                           push_speed_mps=params.push_speed_mps)


def derived_seed(seed: int, object_id: str, round_index: int, purpose: str) -> int:
    """A 63-bit seed from (build seed, object, round, purpose): independent of scheduling."""
    digest = hashlib.sha256(f"gd2p-dataset:{seed}:{object_id}:{round_index}:{purpose}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & (2**63 - 1)


def physics_defaults() -> dict[str, Any]:
    """Every push-simulation setting of this code (the validator's defaults for what a job does not send)."""
    return dataclasses.asdict(PhysicsParams())


def code_version() -> str:
    """The project version, plus the git commit when run from a checkout (provenance of every row)."""
    try:
        version = metadata.version("gd2p-zenoh")
    except metadata.PackageNotFoundError:
        version = "unknown"
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).resolve().parent,
                                capture_output=True, text=True, timeout=5, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return version
    return f"{version}+g{commit}" if commit else version


# ----------------------------------------------------------------------------- placements
@dataclass(frozen=True)
class Placement:
    """Where one round puts the object in D: resting pose `pose_index` turned by `yaw_rad` about z."""

    pose_index: int
    yaw_rad: float


@dataclass(frozen=True)
class RestingPoses:
    """What the placement draw needs of an object: its resting poses' stabilities and its default pose."""

    probabilities: tuple[float, ...]
    default_index: int

    @classmethod
    def of(cls, obj: ObjectModel) -> RestingPoses:
        return cls(tuple(float(p.probability) for p in obj.resting_poses), obj.default_pose_index)


def choose_placement(settings: BuildSettings, object_id: str, round_index: int, poses: RestingPoses) -> Placement:
    """Round `round_index`'s placement (module docstring): seeded by (build seed, object, round) only."""
    if settings.placement == "default":
        return Placement(poses.default_index, 0.0)
    rng = np.random.default_rng(derived_seed(settings.seed, object_id, round_index, "placement"))
    yaw = float(rng.uniform(-math.pi, math.pi))
    if round_index == 0:
        return Placement(poses.default_index, yaw)
    weights = np.maximum(np.asarray(poses.probabilities, dtype=np.float64), MIN_POSE_PROBABILITY)
    return Placement(int(rng.choice(len(weights), p=weights / weights.sum())), yaw)


def placement_frame(obj: ObjectModel, placement: Placement) -> DirectionFrame | None:
    """The floating-hand ValidationJob frame that places `obj` as `placement` says (D = world, push along +x).

    None at yaw 0: the validator's frame-less placement is yaw 0 exactly, where a frame's round trip through
    a quaternion is off by ~1e-16 rad - enough to flip a chaotic push, so `placement="default"` builds would
    not give version 1's rows.
    """
    if placement.yaw_rad == 0.0:
        return None
    return DirectionFrame(object_pose=object_pose(obj.T_D_O(placement.pose_index, placement.yaw_rad)), yaw_deg=0.0)


# ----------------------------------------------------------------------------- object selection
def _object_rank(object_id: str) -> tuple[int, str]:
    """The library's first generation before the everyday families, each in a fixed hash order."""
    return library_generation(object_id), hashlib.sha256(f"gd2p-dataset-order:{object_id}".encode()).hexdigest()


def select_objects(split: str, count: int | None = None, object_ids: Sequence[str] | None = None,
                   allow_split: bool = False) -> list[str]:
    """The objects of a build, in build order.

    Explicit `object_ids` must all belong to `split`; otherwise the first `count` objects of the
    split in a fixed hash order (which mixes the random and procedural families, and lets a larger
    `count` extend a smaller build), the everyday procedural families after the rest of the library
    (`library_generation`): a count chosen before they existed picks the same objects. A build of
    the whole split (no count) has them all, in hash order alone (every family interleaved). Data
    for a split other than train is refused unless `allow_split`: test objects are never used for training.
    """
    if split != TRAINING_SPLIT and not allow_split:
        raise BuildError(f"refusing to build training data from the {split!r} split: only {TRAINING_SPLIT!r} objects "
                         "may be used for training (test objects never are); pass --allow-split to build "
                         "evaluation data on purpose")
    if object_ids:
        for oid in object_ids:
            if is_final_id(oid):  # never: not even inside the final-split evaluation
                raise BuildError(f"{oid} is an object of the final split: it is measured once per release by "
                                 "`gd2p eval EXPERIMENT --split final` only, and no data is ever built from it")
        unknown = sorted(set(object_ids) - set(list_object_ids()))
        if unknown:
            raise BuildError(f"unknown library object id(s): {unknown[:8]} (see `gd2p objects list`)")
        wrong = {oid: split_of(oid) for oid in object_ids if split_of(oid) != split}
        if wrong:
            raise BuildError(f"objects not in the {split!r} split: "
                             + ", ".join(f"{oid} ({s})" for oid, s in list(wrong.items())[:8])
                             + ("; test objects are never used for training" if "test" in wrong.values() else ""))
        return list(dict.fromkeys(object_ids))
    if count is None:
        # A whole-split build interleaves every family, so a build stopped part-way (and resumed in a
        # later session) is already a sample of all of them rather than of the first generation only.
        return sorted(list_object_ids(split), key=lambda oid: _object_rank(oid)[1])
    if count < 1:
        raise BuildError(f"--objects must be >= 1, got {count}")
    return sorted(list_object_ids(split), key=_object_rank)[:count]


# ----------------------------------------------------------------------------- live figures
@dataclass
class BuildCounters:
    """Running totals of one build run (this run only, not the resumed part)."""

    started: float = field(default_factory=time.monotonic)
    objects_done: int = 0
    objects_failed: int = 0
    objects_skipped: int = 0
    generated: int = 0
    raw_successes: int = 0
    augmented_validated: int = 0
    augmented_successes: int = 0
    stored_rows: int = 0  # successes and failures
    generated_validated: int = 0  # candidates whose validation came back
    generation_s: float = 0.0  # worker-reported compute time, summed over jobs: what the build spends where
    validation_s: float = 0.0

    @property
    def elapsed_s(self) -> float:
        return time.monotonic() - self.started

    @property
    def validated_pushes(self) -> int:
        return self.generated_validated + self.augmented_validated

    @property
    def successes(self) -> int:
        """Successful poses (raw and augmented) this run: the training poses it added."""
        return self.raw_successes + self.augmented_successes

    def rates(self) -> dict[str, float]:
        """Throughput and per-stage success rates so far."""
        elapsed = max(self.elapsed_s, 1e-9)
        return {
            "candidates_per_s": self.generated / elapsed,
            "validated_pushes_per_s": self.validated_pushes / elapsed,
            "raw_success_rate": self.raw_successes / self.generated_validated if self.generated_validated else 0.0,
            "augmented_success_rate": (self.augmented_successes / self.augmented_validated
                                       if self.augmented_validated else 0.0),
        }

    @property
    def successes_per_compute_core_h(self) -> float:
        """Successful poses per core-hour of the workers' job time (their CPU time when each has a core to itself;
        more when they share one). Object loading and process start-up are not in it."""
        compute_h = (self.generation_s + self.validation_s) / 3600.0
        return self.successes / compute_h if compute_h else 0.0

    def summary(self) -> dict[str, Any]:
        figures = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in asdict(self).items() if k != "started"}
        rates = {k: round(v, 4) for k, v in self.rates().items()}
        return {**figures, "validated_pushes": self.validated_pushes, "successes": self.successes,
                "successes_per_compute_core_h": round(self.successes_per_compute_core_h, 1),
                "wall_s": round(self.elapsed_s, 3), **rates}


ProgressCallback = Callable[[BuildCounters, str | None], None]  # (counters, id of an object just finished)


# ----------------------------------------------------------------------------- per-object work
@dataclass
class _ObjectWork:
    object_id: str
    model: ObjectModel
    round: int = 0
    tables: list[pa.Table] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(COUNT_KEYS, 0))
    placements: list[Placement] = field(default_factory=list)  # one per round so far
    started: float = field(default_factory=time.monotonic)
    generation: GenerationResult | None = None
    generation_s: float = 0.0
    validation_s: float = 0.0

    @property
    def stored(self) -> int:
        """Successful poses so far (the measure of `min_poses`)."""
        return self.counts["raw_successes"] + self.counts["augmented_successes"]

    @property
    def placement(self) -> Placement:
        return self.placements[-1]


class DataEngine:
    """Runs a build over the generator and validator dispatchers into a `DatasetStore`."""

    def __init__(self, generators: Dispatcher, validators: Dispatcher, store: DatasetStore, settings: BuildSettings,
                 generation_in_flight: int = 2, progress: ProgressCallback | None = None):
        self.generators = generators
        self.validators = validators
        self.store = store
        self.settings = settings
        self.generation_in_flight = max(1, generation_in_flight)
        self.progress = progress
        self.counters = BuildCounters()
        self.code_version = code_version()
        self.failures: dict[str, str] = {}

    def run(self, object_ids: Iterable[str]) -> BuildCounters:
        """Build every object not yet in the store; returns this run's figures."""
        done = self.store.completed_objects()
        requested = list(object_ids)
        todo = deque(oid for oid in requested if oid not in done)
        self.counters.objects_skipped = len(requested) - len(todo)
        in_flight: dict[Future[Message], tuple[_ObjectWork, str]] = {}
        while todo or in_flight:
            while todo and sum(stage == "generate" for _, stage in in_flight.values()) < self.generation_in_flight:
                work = self._start(todo.popleft())
                if work is not None:
                    in_flight[self._submit_generation(work)] = (work, "generate")
            finished, _ = wait(list(in_flight), return_when=FIRST_COMPLETED)
            for future in finished:
                work, stage = in_flight.pop(future)
                follow_up = self._advance(work, stage, future)
                if follow_up is not None:
                    in_flight[follow_up[0]] = (work, follow_up[1])
        return self.counters

    # ------------------------------------------------------------------ one step of one object
    def _start(self, object_id: str) -> _ObjectWork | None:
        """The object's work with its first placement; None (recorded as a failure) if it does not load here."""
        try:
            model = load_object(object_id)
        except ObjectLoadError as exc:
            self.failures[object_id] = f"load: {exc}"
            self.counters.objects_failed += 1
            self._report(object_id)
            return None
        work = _ObjectWork(object_id, model)
        work.placements.append(self._placement(work))
        return work

    def _placement(self, work: _ObjectWork) -> Placement:
        return choose_placement(self.settings, work.object_id, work.round, RestingPoses.of(work.model))

    def _advance(self, work: _ObjectWork, stage: str, future: Future[Message]) -> tuple[Future[Message], str] | None:
        """Handle a reply; returns the object's next job (future, stage) or None when it is finished."""
        try:
            reply = future.result()
        except DispatchError as exc:
            raise BuildError(f"{work.object_id}: no {stage} worker answered: {exc}") from exc
        if isinstance(reply, ErrorReply):
            if reply.code != "bad_request":
                raise BuildError(f"{work.object_id}: the {stage} service failed ({reply.code}): {reply.message}")
            self._fail(work, f"{stage}: {reply.message}")
            return None
        if stage == "generate":
            assert isinstance(reply, GenerationResult)
            work.generation = reply
            work.generation_s += reply.elapsed_s
            self.counters.generation_s += reply.elapsed_s
            work.counts["generated"] += len(reply.poses.to_numpy())
            self.counters.generated += len(reply.poses.to_numpy())
            self._report(None)
            return self._submit_validation(work), "validate"
        assert isinstance(reply, ValidationResult)
        work.validation_s += reply.elapsed_s
        self.counters.validation_s += reply.elapsed_s
        self._absorb_validation(work, reply)
        if self._another_round(work):
            work.round += 1
            work.placements.append(self._placement(work))
            return self._submit_generation(work), "generate"
        self._finish(work)
        return None

    def _another_round(self, work: _ObjectWork) -> bool:
        s = self.settings
        wanted = work.round + 1 < s.min_rounds or work.stored < s.min_poses
        return wanted and work.round + 1 < s.max_rounds

    def _submit_generation(self, work: _ObjectWork) -> Future[Message]:
        s, placement = self.settings, work.placement
        job = GenerationJob(object=ObjectRef(library_id=work.object_id),
                            hand=s.hand, batch_size=s.per_object, iterations=s.iterations,
                            seed=derived_seed(s.seed, work.object_id, work.round, "generate"),
                            pose_index=placement.pose_index, yaw_rad=placement.yaw_rad)
        return self.generators.submit(job)

    def _submit_validation(self, work: _ObjectWork) -> Future[Message]:
        s, placement = self.settings, work.placement
        assert work.generation is not None
        job = ValidationJob(object=ObjectRef(library_id=work.object_id),
                            hand=s.hand, poses=work.generation.poses, augment=True,
                            seed=derived_seed(s.seed, work.object_id, work.round, "validate"),
                            push_distance_m=s.push_distance_m, settings=PhysicsSettings(**s.physics),
                            pose_index=placement.pose_index, frame=placement_frame(work.model, placement))
        return self.validators.submit(job)

    def _absorb_validation(self, work: _ObjectWork, result: ValidationResult) -> None:
        assert work.generation is not None
        success = result.success.to_numpy().astype(bool)
        augmented = result.augmented
        aug_success = augmented.success.to_numpy().astype(bool) if augmented is not None else np.zeros(0, bool)
        work.counts["raw_successes"] += int(success.sum())
        work.counts["augmented_validated"] += len(aug_success)
        work.counts["augmented_successes"] += int(aug_success.sum())
        self.counters.generated_validated += len(success)
        self.counters.raw_successes += int(success.sum())
        self.counters.augmented_validated += len(aug_success)
        self.counters.augmented_successes += int(aug_success.sum())
        work.tables.append(pose_rows(work.object_id, work.round, work.placement, work.generation, result,
                                     self.settings, self.code_version))
        work.generation = None
        self._report(None)

    def _finish(self, work: _ObjectWork) -> None:
        rows = pa.concat_tables(work.tables) if work.tables else empty_rows()
        stats = {**work.counts, "rounds": work.round + 1, "family": work.model.family,
                 "placements": [{"round": r, "pose_index": p.pose_index, "yaw_rad": p.yaw_rad}
                                for r, p in enumerate(work.placements)],
                 "elapsed_s": round(time.monotonic() - work.started, 3),
                 "generation_s": round(work.generation_s, 3), "validation_s": round(work.validation_s, 3)}
        self.store.write_object(work.object_id, rows, stats)
        self.counters.objects_done += 1
        self.counters.stored_rows += rows.num_rows
        self._report(work.object_id)

    def _fail(self, work: _ObjectWork, message: str) -> None:
        """A deterministic refusal (unusable object): recorded, not stored, retried on the next run."""
        self.failures[work.object_id] = message
        self.counters.objects_failed += 1
        self._report(work.object_id)

    def _report(self, object_id: str | None) -> None:
        if self.progress is not None:
            self.progress(self.counters, object_id)


# ----------------------------------------------------------------------------- rows
def _schema() -> pa.Schema:
    fields = [
        ("object_id", pa.string()), ("hand", pa.string()), ("pose", pa.list_(pa.float32())),
        ("pose_index", pa.int32()), ("yaw_rad", pa.float64()), ("stage", pa.string()), ("success", pa.bool_()),
        ("pose_id", pa.string()), ("parent_id", pa.string()), ("round", pa.int32()), ("candidate_index", pa.int32()),
        ("generator_seed", pa.int64()), ("validation_seed", pa.int64()),
        ("position_error_m", pa.float32()), ("rotation_deg", pa.float32()), ("max_tilt_deg", pa.float32()),
        ("toppled", pa.bool_()), ("contact_kept", pa.bool_()), ("hand_table_contact", pa.bool_()),
        ("initial_penetration_m", pa.float32()),
        *[(f"energy_{t}", pa.float32()) for t in ENERGY_TERMS],
        ("max_penetration_m", pa.float32()), ("palm_normal_x", pa.float32()),
        ("solver_iterations", pa.int32()), ("time_step_s", pa.float64()), ("push_speed_mps", pa.float64()),
        ("push_distance_m", pa.float64()), ("code_version", pa.string()),
    ]
    return pa.schema(fields)


SCHEMA = _schema()


def empty_rows() -> pa.Table:
    return SCHEMA.empty_table()


def pose_rows(object_id: str, round_index: int, placement: Placement, generation: GenerationResult,
              validation: ValidationResult, settings: BuildSettings, version: str) -> pa.Table:
    """Every raw candidate and every augmented copy of one round, with its outcome, as store rows."""
    columns: dict[str, list[Any]] = {name: [] for name in SCHEMA.names}
    _add_raw_rows(columns, f"{object_id}/r{round_index}", generation, validation)
    if validation.augmented is not None:
        _add_augmented_rows(columns, f"{object_id}/r{round_index}", validation)
    n = len(columns["stage"])
    constants = {
        "object_id": object_id, "hand": settings.hand, "pose_index": placement.pose_index,
        "yaw_rad": placement.yaw_rad, "round": round_index,
        "generator_seed": derived_seed(settings.seed, object_id, round_index, "generate"),
        "validation_seed": derived_seed(settings.seed, object_id, round_index, "validate"),
        "solver_iterations": settings.physics["solver_iterations"], "time_step_s": settings.physics["time_step_s"],
        "push_speed_mps": settings.physics["push_speed_mps"], "push_distance_m": settings.push_distance_m,
        "code_version": version,
    }
    for name, value in constants.items():
        columns[name] = [value] * n
    # The judge's topple angle applied to the largest lean during the push (the validator reports no final tilt):
    # an object that leaned past it and fell back counts as toppled too.
    columns["toppled"] = [tilt > TOPPLED_TILT_DEG for tilt in columns["max_tilt_deg"]]
    return pa.table(columns, schema=SCHEMA)


def _add_raw_rows(columns: dict[str, list[Any]], prefix: str, generation: GenerationResult,
                  validation: ValidationResult) -> None:
    """The generator's candidates in order, with their energies and push outcomes."""
    poses = generation.poses.to_numpy()
    outcomes = {c: getattr(validation, c).to_numpy() for c in OUTCOME_COLUMNS}
    energies = {t: generation.energies[t].to_numpy() if t in generation.energies else None for t in ENERGY_TERMS}
    penetration = generation.max_penetration_m.to_numpy()
    palm_x = generation.palm_normals.to_numpy()[:, 0]
    for i, pose in enumerate(poses):
        _add_row(columns, "raw", pose, f"{prefix}/c{i}", None, i, {c: v[i] for c, v in outcomes.items()})
        for t in ENERGY_TERMS:
            values = energies[t]
            columns[f"energy_{t}"].append(None if values is None else float(values[i]))
        columns["max_penetration_m"].append(float(penetration[i]))
        columns["palm_normal_x"].append(float(palm_x[i]))


def _add_augmented_rows(columns: dict[str, list[Any]], prefix: str, validation: ValidationResult) -> None:
    """The Halton copies (of successful candidates only) in order, numbered per parent; no generator figures."""
    augmented = validation.augmented
    assert augmented is not None
    outcomes = {c: getattr(augmented, c).to_numpy() for c in OUTCOME_COLUMNS}
    poses = augmented.poses.to_numpy()
    copy_number: dict[int, int] = {}
    for j, parent in enumerate(augmented.parent_index.to_numpy().tolist()):
        copy = copy_number[parent] = copy_number.get(parent, -1) + 1
        _add_row(columns, "augmented", poses[j], f"{prefix}/c{parent}/a{copy}", f"{prefix}/c{parent}", parent,
                 {c: v[j] for c, v in outcomes.items()})
        for name in [f"energy_{t}" for t in ENERGY_TERMS] + ["max_penetration_m", "palm_normal_x"]:
            columns[name].append(None)


def _add_row(columns: dict[str, list[Any]], stage: str, pose: np.ndarray, pose_id: str, parent: str | None,
             candidate: int, outcome: dict[str, np.generic]) -> None:
    columns["stage"].append(stage)
    columns["pose"].append(pose.astype(np.float32).tolist())
    columns["pose_id"].append(pose_id)
    columns["parent_id"].append(parent)
    columns["candidate_index"].append(int(candidate))
    for c in OUTCOME_COLUMNS:
        columns[c].append(outcome[c].item())


def run_record(command: Sequence[str], counters: BuildCounters, workers: dict[str, int],
               failures: dict[str, str], settings: BuildSettings) -> dict[str, Any]:
    """The manifest's record of one build run: command line, commit, physics, wall time, machine and figures."""
    return {"command": list(command), "finished_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "machine": {"host": platform.node(), "cpus": os.cpu_count(), "python": platform.python_version()},
            "workers": workers, "code_version": code_version(), "commit": git_commit(),
            "physics": {"sent": dict(settings.physics), "validator_defaults": physics_defaults()},
            "failures": failures, **counters.summary()}


def git_commit() -> str | None:
    """The checkout's full commit, "-dirty" when tracked files differ from it; None outside a checkout."""
    here = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True,
                                timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return f"{commit}-dirty" if dirty else commit or None

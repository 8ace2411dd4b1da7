"""The data engine: objects -> generator -> validator (+ Halton augmentation) -> pose store.

A client of the generator and validator services over the bus (two `Dispatcher`s); it never calls
their algorithms directly, so the same build runs on one laptop or on a farm of workers joined to
one router. For each object, in a fixed order:

    round r = 0, 1, ...:
        GenerationJob(object, hand, batch_size = per_object, seed = f(seed, object, r, "generate"))
        ValidationJob(the candidates, augment=True, seed = f(seed, object, r, "validate"))
        keep the successful candidates and their successful augmented copies
    until the object has `min_poses` stored poses or `max_rounds` rounds ran (one round by default)
    store.write_object(...)   # one atomic shard + manifest update per object

Every seed is derived from (build seed, object id, round), never from scheduling, and both services
are deterministic for a seed, so an object's rows do not depend on which worker ran it, on how many
objects were in flight, or on whether the build was interrupted and resumed: a resumed build skips
the objects the manifest marks done and ends with the same rows as an uninterrupted one.

Several objects are in flight at once (one more generation job than there are generator workers,
and every finished generation goes straight to the validators), so every worker stays busy.
"""
from __future__ import annotations

import hashlib
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

import numpy as np
import pyarrow as pa

from shared.bus import Dispatcher, DispatchError
from shared.contracts.messages import (
    ErrorReply,
    GenerationJob,
    GenerationResult,
    ObjectRef,
    PhysicsSettings,
    ValidationJob,
    ValidationResult,
)
from shared.data.dataset_store import COUNT_KEYS, DatasetStore
from shared.world.objects import library_generation, list_object_ids, split_of
from shared.world.sim import PhysicsParams

TRAINING_SPLIT = "train"
ENERGY_TERMS = ("fc", "dis", "pen", "spen", "joints", "ff", "fp", "tpen", "dir", "arm", "total")
OUTCOME_COLUMNS = ("position_error_m", "rotation_deg", "max_tilt_deg", "contact_kept", "hand_table_contact",
                   "initial_penetration_m")


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
    min_poses: int = 0  # run more rounds while an object has fewer stored poses than this ...
    max_rounds: int = 1  # ... up to this many rounds
    push_distance_m: float = 0.20
    physics: dict = field(default_factory=lambda: default_physics().model_dump())

    def __post_init__(self) -> None:
        if self.per_object < 1:
            raise BuildError(f"--per-object must be >= 1, got {self.per_object}")
        if self.max_rounds < 1:
            raise BuildError(f"--max-rounds must be >= 1, got {self.max_rounds}")
        if self.min_poses < 0:
            raise BuildError(f"--min-poses must be >= 0, got {self.min_poses}")

    def parameters(self) -> dict:
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
    the whole split (no count) has them all. Data for a split other than train is refused unless
    `allow_split`: test objects are never used for training.
    """
    if split != TRAINING_SPLIT and not allow_split:
        raise BuildError(f"refusing to build training data from the {split!r} split: only {TRAINING_SPLIT!r} objects "
                         "may be used for training (test objects never are); pass --allow-split to build "
                         "evaluation data on purpose")
    if object_ids:
        unknown = sorted(set(object_ids) - set(list_object_ids()))
        if unknown:
            raise BuildError(f"unknown library object id(s): {unknown[:8]} (see `gd2p objects list`)")
        wrong = {oid: split_of(oid) for oid in object_ids if split_of(oid) != split}
        if wrong:
            raise BuildError(f"objects not in the {split!r} split: "
                             + ", ".join(f"{oid} ({s})" for oid, s in list(wrong.items())[:8])
                             + ("; test objects are never used for training" if "test" in wrong.values() else ""))
        return list(dict.fromkeys(object_ids))
    ranked = sorted(list_object_ids(split), key=_object_rank)
    if count is not None:
        if count < 1:
            raise BuildError(f"--objects must be >= 1, got {count}")
        ranked = ranked[:count]
    return ranked


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
    stored_rows: int = 0
    generated_validated: int = 0  # candidates whose validation came back
    generation_s: float = 0.0  # worker-reported compute time, summed over jobs: what the build spends where
    validation_s: float = 0.0

    @property
    def elapsed_s(self) -> float:
        return time.monotonic() - self.started

    @property
    def validated_pushes(self) -> int:
        return self.generated_validated + self.augmented_validated

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

    def summary(self) -> dict:
        figures = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in asdict(self).items() if k != "started"}
        rates = {k: round(v, 4) for k, v in self.rates().items()}
        return {**figures, "validated_pushes": self.validated_pushes, "wall_s": round(self.elapsed_s, 3), **rates}


ProgressCallback = Callable[[BuildCounters, str | None], None]  # (counters, id of an object just finished)


# ----------------------------------------------------------------------------- per-object work
@dataclass
class _ObjectWork:
    object_id: str
    round: int = 0
    tables: list[pa.Table] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(COUNT_KEYS, 0))
    started: float = field(default_factory=time.monotonic)
    generation: GenerationResult | None = None
    generation_s: float = 0.0
    validation_s: float = 0.0

    @property
    def stored(self) -> int:
        return self.counts["raw_successes"] + self.counts["augmented_successes"]


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
        in_flight: dict[Future, tuple[_ObjectWork, str]] = {}
        while todo or in_flight:
            while todo and sum(stage == "generate" for _, stage in in_flight.values()) < self.generation_in_flight:
                work = _ObjectWork(todo.popleft())
                in_flight[self._submit_generation(work)] = (work, "generate")
            finished, _ = wait(list(in_flight), return_when=FIRST_COMPLETED)
            for future in finished:
                work, stage = in_flight.pop(future)
                follow_up = self._advance(work, stage, future)
                if follow_up is not None:
                    in_flight[follow_up[0]] = (work, follow_up[1])
        return self.counters

    # ------------------------------------------------------------------ one step of one object
    def _advance(self, work: _ObjectWork, stage: str, future: Future) -> tuple[Future, str] | None:
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
        if work.stored < self.settings.min_poses and work.round + 1 < self.settings.max_rounds:
            work.round += 1
            return self._submit_generation(work), "generate"
        self._finish(work)
        return None

    def _submit_generation(self, work: _ObjectWork) -> Future:
        s = self.settings
        job = GenerationJob(object=ObjectRef(library_id=work.object_id),
                            hand=s.hand, batch_size=s.per_object, iterations=s.iterations,
                            seed=derived_seed(s.seed, work.object_id, work.round, "generate"))
        return self.generators.submit(job)

    def _submit_validation(self, work: _ObjectWork) -> Future:
        s = self.settings
        assert work.generation is not None
        job = ValidationJob(object=ObjectRef(library_id=work.object_id),
                            hand=s.hand, poses=work.generation.poses, augment=True,
                            seed=derived_seed(s.seed, work.object_id, work.round, "validate"),
                            push_distance_m=s.push_distance_m, settings=PhysicsSettings(**s.physics))
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
        work.tables.append(pose_rows(work.object_id, work.round, work.generation, result, self.settings,
                                     self.code_version))
        work.generation = None
        self._report(None)

    def _finish(self, work: _ObjectWork) -> None:
        rows = pa.concat_tables(work.tables) if work.tables else empty_rows()
        stats = {**work.counts, "rounds": work.round + 1, "elapsed_s": round(time.monotonic() - work.started, 3),
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
        ("pose_index", pa.int32()), ("yaw_rad", pa.float64()), ("stage", pa.string()), ("pose_id", pa.string()),
        ("parent_id", pa.string()), ("round", pa.int32()), ("candidate_index", pa.int32()),
        ("generator_seed", pa.int64()), ("validation_seed", pa.int64()),
        ("position_error_m", pa.float32()), ("rotation_deg", pa.float32()), ("max_tilt_deg", pa.float32()),
        ("contact_kept", pa.bool_()), ("hand_table_contact", pa.bool_()), ("initial_penetration_m", pa.float32()),
        *[(f"energy_{t}", pa.float32()) for t in ENERGY_TERMS],
        ("max_penetration_m", pa.float32()), ("palm_normal_x", pa.float32()),
        ("solver_iterations", pa.int32()), ("time_step_s", pa.float64()), ("push_speed_mps", pa.float64()),
        ("push_distance_m", pa.float64()), ("code_version", pa.string()),
    ]
    return pa.schema(fields)


SCHEMA = _schema()


def empty_rows() -> pa.Table:
    return SCHEMA.empty_table()


def pose_rows(object_id: str, round_index: int, generation: GenerationResult, validation: ValidationResult,
              settings: BuildSettings, version: str) -> pa.Table:
    """The successful raw candidates and successful augmented copies of one round, as store rows."""
    raw_ok = np.flatnonzero(validation.success.to_numpy())
    raw_poses = generation.poses.to_numpy()
    energies = {t: generation.energies[t].to_numpy() if t in generation.energies else None for t in ENERGY_TERMS}
    penetration = generation.max_penetration_m.to_numpy()
    palm_x = generation.palm_normals.to_numpy()[:, 0]
    prefix = f"{object_id}/r{round_index}"

    columns: dict[str, list] = {name: [] for name in SCHEMA.names}
    raw_outcomes = {c: getattr(validation, c).to_numpy() for c in OUTCOME_COLUMNS}

    def add(stage: str, pose: np.ndarray, pose_id: str, parent: str | None, candidate: int,
            outcomes: dict[str, np.ndarray], row: int, generator_row: int | None) -> None:
        columns["stage"].append(stage)
        columns["pose"].append(pose.astype(np.float32).tolist())
        columns["pose_id"].append(pose_id)
        columns["parent_id"].append(parent)
        columns["candidate_index"].append(candidate)
        for c in OUTCOME_COLUMNS:
            columns[c].append(outcomes[c][row].item())
        for t in ENERGY_TERMS:
            values = energies[t]
            columns[f"energy_{t}"].append(None if generator_row is None or values is None else float(values[generator_row]))
        columns["max_penetration_m"].append(None if generator_row is None else float(penetration[generator_row]))
        columns["palm_normal_x"].append(None if generator_row is None else float(palm_x[generator_row]))

    for i in raw_ok:
        add("raw", raw_poses[i], f"{prefix}/c{i}", None, int(i), raw_outcomes, int(i), int(i))
    augmented = validation.augmented
    if augmented is not None:
        aug_ok = augmented.success.to_numpy()
        parents = augmented.parent_index.to_numpy()
        aug_poses = augmented.poses.to_numpy()
        aug_outcomes = {c: getattr(augmented, c).to_numpy() for c in OUTCOME_COLUMNS}
        copy_number: dict[int, int] = {}
        for j, parent in enumerate(parents.tolist()):
            copy = copy_number[parent] = copy_number.get(parent, -1) + 1
            if aug_ok[j]:
                add("augmented", aug_poses[j], f"{prefix}/c{parent}/a{copy}", f"{prefix}/c{parent}", parent,
                    aug_outcomes, j, None)

    n = len(columns["stage"])
    constants = {
        "object_id": object_id, "hand": settings.hand, "pose_index": None, "yaw_rad": 0.0, "round": round_index,
        "generator_seed": derived_seed(settings.seed, object_id, round_index, "generate"),
        "validation_seed": derived_seed(settings.seed, object_id, round_index, "validate"),
        "solver_iterations": settings.physics["solver_iterations"], "time_step_s": settings.physics["time_step_s"],
        "push_speed_mps": settings.physics["push_speed_mps"], "push_distance_m": settings.push_distance_m,
        "code_version": version,
    }
    for name, value in constants.items():
        columns[name] = [value] * n
    return pa.table(columns, schema=SCHEMA)


def run_record(command: Sequence[str], counters: BuildCounters, workers: dict[str, int],
               failures: dict[str, str]) -> dict:
    """The manifest's record of one build run: command line, wall time, machine and figures."""
    return {"command": list(command), "finished_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "machine": {"host": platform.node(), "cpus": os.cpu_count(), "python": platform.python_version()},
            "workers": workers, "code_version": code_version(), "failures": failures, **counters.summary()}

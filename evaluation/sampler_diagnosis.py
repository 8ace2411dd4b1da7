"""Sampler diagnosis on training objects: `gd2p eval sampler-diagnosis`.

Before scaling the data, three questions decide how much of the gap between diffusion samples and
Nearest Neighbor's stored poses (version 1: the stored poses validated about twice as often on test
objects) is the model and how much the data:

1. **Does the model reproduce its own training data?** On objects of the shipped checkpoint's
   training set: the validated fraction of 200 diffusion samples (the version-1 Allegro checkpoint
   `allegro_v1.pt`, no longer shipped: `diagnosed_files` restores it from git history; DDPM-100, placed and seeded as `gd2p sample --validate` and `gd2p eval sampler-quality` do)
   against that of the same objects' stored poses (the training dataset's poses of the object).
2. **Does the model use the geometry at all?** The same objects sampled with the BPS of *another*
   training object (of another family where possible) and validated on their own geometry.
3. **Is the BPS computed the same way at inference as in training?** For every selected object,
   the BPS along the training path, the one the NN index stores, and the sampler service's path;
   their max abs difference, the encoding settings (basis, surface samples) each path uses, and
   the BPS the planner's frames give (the evaluation's push directions).

Where the stored poses come from: the training dataset (`data/allegro-train`, built by the
`gd2p dataset build` command of docs/usage.md) is not in the repository, but the version-1 Nearest-Neighbor index
`allegro_v1_nn.npz` (restored from git history with the checkpoint) is built from the same store (the manifests' dataset
SHA-256 agree; checked on every run) and holds, per training frame (222 objects, each in its
default resting pose at yaw 0), the frame's BPS (float16) and every stored pose (9,683). A
`StoredPosesSource` returns an object's own frame, found by id, not by BPS.

Objects: the shipped checkpoint trained on 200 of the dataset's 222 objects and held 22 out for its
validation loss (`shared.sampling.train.split_object_ids` with the manifest's settings). The
diagnosis takes `trained` (12) objects of the first group and `held_out` (4) of the second, each
round-robin over families (the largest family first; within a family the issue's first-look objects
rnd-000 and proc-box-003 first, then the order of a seeded hash): held-out objects are in the
training split of the library and in the dataset, but the model never saw them, so they separate
"cannot reproduce" from "cannot generalise". Question 2 runs on the trained group only.

Protocol: `evaluation.coverage` with every sampled pose pushed (fraction window = samples: 200), each
object resting in its default pose at the origin, pushed 0.20 m along +x by the floating hand
(validator default physics, the data engine's criterion). Rates are pooled over poses with 95%
intervals from the bootstrap over objects (`evaluation.stats`); differences are paired by object.
Every object of every source is one record in `<out>/sampler-diagnosis/records.jsonl`: a killed run
resumes where it stopped.

Budget (full run): 12 x (200 diffusion + 200 shuffled) + 4 x 200 diffusion + the 16 objects' 772 stored
poses = 6,372 pushes. The `--quick` smoke run measured 0.10-0.17 worker-seconds per push (sampling
included) on a shared 2-core machine; bench/validator.py's 4.4 pushes/s per process is 0.23 s. So
about 11-25 CPU-minutes: 6-13 min with `--workers 2` on two idle cores. Question 3 takes seconds.
"""
from __future__ import annotations

import hashlib
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from evaluation.coverage import (
    HAND,
    CoverageError,
    CoveragePool,
    CoverageSettings,
    DiffusionSource,
    NearestNeighborSource,
    PoseSource,
    pose_trials,
    summarize,
)
from evaluation.report import CODE_AT_START, markdown_table, write_experiment
from evaluation.sampler_quality import index_fingerprint
from evaluation.stats import Interval, difference_interval, success_interval
from evaluation.store import ResultStore

if TYPE_CHECKING:
    from shared.world.objects import ObjectModel

NAME = "sampler-diagnosis"
TITLE = "Sampler diagnosis: training objects, shuffled BPS, BPS paths"
SELECTION_SEED = 0
FIRST_LOOK_OBJECTS = ("rnd-000", "proc-box-003")  # the issue's first look: 94/200 and 59/200 vs 50/55 and 38/39
SAME_TOLERANCE = 1e-6  # metres: two BPS "agree" when no feature differs by more (float32 rounding is ~3e-8)
MOVED_PLACEMENT = (0.55, -0.20, 135.0)  # another world position and yaw, the push turned with the object


@dataclass(frozen=True)
class DiagnosisSettings:
    """What fixes a diagnosis run (pinned in its store)."""

    trained: int = 12  # objects the checkpoint trained on
    held_out: int = 4  # dataset objects the checkpoint held out for its validation loss
    samples: int = 200  # diffusion samples per object, every one pushed
    selection_seed: int = SELECTION_SEED

    def coverage(self) -> CoverageSettings:
        """Every pose pushed: the validated fraction is over all samples (no early stopping)."""
        return CoverageSettings(samples=self.samples, fraction_poses=self.samples, chunk=self.samples, hand=HAND)

    def to_dict(self) -> dict[str, Any]:
        return {"trained": self.trained, "held_out": self.held_out, "samples": self.samples,
                "selection_seed": self.selection_seed}


FULL = DiagnosisSettings()
QUICK = DiagnosisSettings(trained=2, held_out=1, samples=16)


# ----------------------------------------------------------------------------- pose sources
@dataclass(frozen=True)
class StoredPosesSource(NearestNeighborSource):
    """An object's own stored poses: its training frame in the NN index, found by object id (not by BPS).

    The frame is the object's default resting pose at yaw 0 in D, the placement `measure_object`
    pushes in (checked). All stored poses, or a seeded subset of k when the frame has more.
    """

    def label(self) -> str:
        return "Stored poses"

    def poses(self, obj: Any, frame: Any, k: int, seed: int) -> np.ndarray:
        from shared.frames import object_yaw_in_d
        from shared.sampling.dataset import DEFAULT_POSE_INDEX, Frame

        if abs(object_yaw_in_d(frame, obj.default_pose.rotation)) > 1e-6:
            raise CoverageError(f"{obj.id}: stored poses are in the default placement (yaw 0 in D), not this frame")
        baseline = self.sampler().index
        return baseline.frame_poses(baseline.frame_row(Frame(obj.id, DEFAULT_POSE_INDEX, 0.0)), k, seed)


@dataclass(frozen=True)
class ShuffledBpsSource(DiffusionSource):
    """Diffusion samples for an object conditioned on another object's BPS (`donors`: object -> donor).

    The donor is encoded exactly as `DiffusionSource` encodes it (its default placement, the
    checkpoint's surface samples and basis), and the object's seed is kept, so an object's shuffled
    samples are the donor's own diffusion samples under that seed.
    """

    donors: tuple[tuple[str, str], ...] = ()

    def label(self) -> str:
        return f"{super().label()}, shuffled BPS"

    def donor_of(self, object_id: str) -> str:
        donor = dict(self.donors).get(object_id)
        if donor is None:
            raise CoverageError(f"{object_id} has no BPS donor")
        return donor

    def poses(self, obj: Any, frame: Any, k: int, seed: int) -> np.ndarray:
        from shared.sampling.sampling import default_frame
        from shared.world.objects import load_object

        donor = load_object(self.donor_of(obj.id))
        sampler = self.pose_sampler()
        bps, _, _ = sampler.encode(donor, default_frame(donor))
        poses: np.ndarray = sampler.sample_from_bps(bps, k, sampler=self.sampler, steps=self.steps, seed=seed)
        return poses


# ----------------------------------------------------------------------------- objects
def family(object_id: str) -> str:
    """The library family of an id (box, cylinder, ..., random), without loading its geometry."""
    from shared.world.objects.catalog import resolve_library_id

    return resolve_library_id(object_id).family


def checkpoint_objects(checkpoint: Path, nn_index: Path) -> tuple[list[str], list[str]]:
    """(trained on, held out for the validation loss): the shipped checkpoint's split of the dataset's objects.

    Recomputed from the NN index's frames (the dataset's objects) with the checkpoint manifest's
    split settings, and checked against the manifest's counts and dataset hash.
    """
    from shared.sampling.checkpoint import load_checkpoint
    from shared.sampling.nearest_neighbor import NearestNeighborBaseline
    from shared.sampling.train import split_object_ids

    manifest = load_checkpoint(checkpoint).manifest
    index = NearestNeighborBaseline.load(nn_index)
    dataset = manifest.get("dataset", {})
    if dataset.get("sha256") != index.manifest.get("dataset", {}).get("sha256"):
        raise CoverageError(f"{nn_index.name} was not built from {checkpoint.name}'s training data (dataset hashes differ)")
    config = manifest["config"]
    trained, held_out = split_object_ids(sorted({f.object_id for f in index.frames}), config["val_fraction"],
                                         config["fraction"], config["seed"])
    if (len(trained), len(held_out)) != (dataset.get("train_objects"), dataset.get("val_objects")):
        raise CoverageError(f"recomputed split {len(trained)} / {len(held_out)} objects differs from {checkpoint.name}'s "
                            f"manifest ({dataset.get('train_objects')} / {dataset.get('val_objects')})")
    return trained, held_out


def pick_objects(pool: Sequence[str], count: int, pinned: Sequence[str] = FIRST_LOOK_OBJECTS,
                 seed: int = SELECTION_SEED) -> list[str]:
    """`count` ids of `pool`, round-robin over families (the largest first, ties by name); within a
    family the `pinned` ids first, then the order of a seeded hash."""
    def rank(object_id: str) -> tuple[bool, str]:
        return object_id not in pinned, hashlib.sha256(f"gd2p-sampler-diagnosis:{seed}:{object_id}".encode()).hexdigest()

    families: dict[str, list[str]] = {}
    for object_id in sorted(pool, key=rank):
        families.setdefault(family(object_id), []).append(object_id)
    queues = [families[name] for name in sorted(families, key=lambda name: (-len(families[name]), name))]
    chosen: list[str] = []
    while len(chosen) < min(count, len(pool)):
        for queue in queues:
            if queue and len(chosen) < count:
                chosen.append(queue.pop(0))
    return chosen


def bps_donors(objects: Sequence[str], seed: int = SELECTION_SEED, attempts: int = 1000) -> dict[str, str]:
    """object -> the object whose BPS its shuffled samples are conditioned on: a seeded derangement
    (no object keeps its own BPS), every donor of another family when the draws find one."""
    if len(objects) < 2 or len(set(objects)) != len(objects):
        raise CoverageError(f"shuffling the BPS needs two or more distinct objects, got {list(objects)}")
    rng = np.random.default_rng(seed)
    fallback: dict[str, str] | None = None
    for _ in range(attempts):
        order = rng.permutation(len(objects))
        if np.any(order == np.arange(len(objects))):
            continue
        donors = {objects[i]: objects[j] for i, j in enumerate(order)}
        if all(family(a) != family(b) for a, b in donors.items()):
            return donors
        fallback = fallback or donors
    if fallback is None:
        raise CoverageError(f"no derangement of {list(objects)} found in {attempts} draws")
    return fallback


# ----------------------------------------------------------------------------- question 3: BPS paths
def placed_frame(obj: Any, x: float, y: float, object_yaw_deg: float, direction_deg: float) -> Any:
    """The DirectionFrame the planner sends: `obj` resting in its default pose at (x, y) turned by
    `object_yaw_deg` in the world, pushed along `direction_deg`."""
    from shared.contracts.messages import DirectionFrame
    from shared.frames import make_transform, yaw_rotation
    from shared.world.push_outcome import object_pose

    T_world_O = make_transform(yaw_rotation(math.radians(object_yaw_deg)), np.array([x, y, 0.0])) @ obj.T_D_O()
    return DirectionFrame(object_pose=object_pose(T_world_O), yaw_deg=direction_deg)


def encoding_settings(sampler: Any, index: Any) -> dict[str, Any]:
    """Basis fingerprint and surface sampling (points, seed) of each path: training, checkpoint, NN index."""
    from shared.sampling.dataset import SURFACE_POINTS, SURFACE_SEED
    from shared.world.bps import BasisPointSet

    return {
        "training": {"basis": BasisPointSet().fingerprint, "surface": [SURFACE_POINTS, SURFACE_SEED]},
        "checkpoint": {"basis": sampler.bps.fingerprint,
                       "surface": [sampler.checkpoint.surface_points, sampler.checkpoint.surface_seed]},
        "nn_index": {"basis": index.bps.fingerprint, "surface": [index.surface_points, index.surface_seed]},
    }


def frame_placements(index: Any) -> dict[str, int]:
    """How many of the index's (the dataset's) frames there are, and how many are an object's default resting pose at yaw 0."""
    from shared.sampling.dataset import DEFAULT_POSE_INDEX

    default = sum(f.pose_index == DEFAULT_POSE_INDEX and abs(f.yaw_rad) < 1e-9 for f in index.frames)
    return {"frames": len(index.frames), "default_placement": int(default)}


def bps_paths(object_id: str, sampler: Any, index: Any, training_bps: Any = None) -> dict[str, Any]:
    """One object's BPS along each path, compared (max abs difference, metres); see the module docstring.

    - training: `shared.sampling.dataset.frame_bps` of the object's frame with `training_bps` (default
      `BasisPointSet()`), what `shared.sampling.train` conditions on;
    - stored: the NN index's float16 BPS of the frame (built by the same `frame_bps`);
    - inference: the sampler service's path, `shared.sampling.server.object_input(ObjectRef)` then
      `PoseSampler.encode` (what `PoseSampler.sample` encodes), in the default placement;
    - moved: the same path with the object elsewhere in the world and the push turned with it (the
      same placement in D: must agree);
    - directions: the evaluation's placement (yaw 0 at OBJECT_XY) pushed along each of its directions,
      which turns the object in D: how far that BPS is from the object's own training BPS and from
      the nearest other training frame's.
    """
    from evaluation.push_protocol import DIRECTIONS_DEG, OBJECT_XY
    from shared.contracts.messages import ObjectRef
    from shared.frames import object_yaw_in_d
    from shared.sampling.dataset import DEFAULT_POSE_INDEX, Frame, frame_bps
    from shared.sampling.sampling import default_frame
    from shared.sampling.server import object_input
    from shared.world.bps import BasisPointSet

    frame = Frame(object_id, DEFAULT_POSE_INDEX, 0.0)
    training = frame_bps([frame], training_bps or BasisPointSet())[0].astype(np.float64)
    row = index.frame_row(frame)
    features = np.asarray(index.frame_features, dtype=np.float64)
    stored = features[row]
    obj = cast("ObjectModel", object_input(ObjectRef(library_id=object_id)))  # a library id loads as a model

    def encode(direction_frame: Any) -> np.ndarray:
        encoded, _, _ = sampler.encode(obj, direction_frame)
        return np.asarray(encoded, dtype=np.float64)

    def neighbours(encoded: np.ndarray) -> dict[str, Any]:
        distances = np.linalg.norm(features - encoded, axis=1)
        others = np.delete(distances, row)
        nearest = int(np.argmin(distances))
        return {"nearest_frame": index.frames[nearest].object_id, "distance_to_own": float(distances[row]),
                "distance_to_nearest_other": float(others.min()) if len(others) else math.nan}

    inference = encode(default_frame(obj))
    moved = encode(placed_frame(obj, *MOVED_PLACEMENT[:2], MOVED_PLACEMENT[2], MOVED_PLACEMENT[2]))
    half_step = np.spacing(np.abs(stored).astype(np.float16)).astype(np.float64) / 2.0  # float16 rounding of `stored`
    directions = []
    for direction in DIRECTIONS_DEG:
        placed = placed_frame(obj, OBJECT_XY[0], OBJECT_XY[1], 0.0, direction)
        encoded = encode(placed)
        directions.append({"direction_deg": direction,
                           "object_yaw_in_d_deg": round(math.degrees(object_yaw_in_d(placed, obj.default_pose.rotation)), 3),
                           "vs_training": float(np.abs(encoded - training).max()), **neighbours(encoded)})
    return {
        "object": object_id,
        "train_vs_inference": float(np.abs(training - inference).max()),
        "stored_vs_inference": float(np.abs(stored - inference).max()),
        "stored_beyond_float16": float(np.max(np.abs(stored - inference) - half_step)),
        "moved_vs_inference": float(np.abs(moved - inference).max()),
        **neighbours(inference),
        "directions": directions,
        "code": CODE_AT_START,
    }


def bps_agree(record: Mapping[str, Any], tolerance: float = SAME_TOLERANCE) -> bool:
    """Whether one object's paths agree: training = inference = moved, stored = inference to float16 rounding,
    and the NN index retrieves the object itself."""
    return (record["train_vs_inference"] <= tolerance and record["moved_vs_inference"] <= tolerance
            and record["stored_beyond_float16"] <= tolerance and record["nearest_frame"] == record["object"])


def settings_agree(settings: Mapping[str, Mapping[str, Any]]) -> bool:
    """Whether every path uses the same basis and the same surface samples."""
    return len({(s["basis"], tuple(s["surface"])) for s in settings.values()}) == 1


def measure_bps(objects: Sequence[str], store: ResultStore, sampler: Any, index: Any) -> list[dict[str, Any]]:
    """The `bps_paths` record of every object (in order); objects already in `store` are not redone."""
    for object_id in objects:
        key = f"bps/{object_id}"
        if not store.done(key):
            store.add(key, bps_paths(object_id, sampler, index))
    return [store.records[f"bps/{object_id}"] for object_id in objects]


# ----------------------------------------------------------------------------- the experiment
# The version-1 checkpoint and NN index left the tree and the wheel (only each hand's current model is shipped);
# git history keeps them: the last commit that shipped them, and where they were.
VERSION_1_COMMIT = "76ddcd8"
VERSION_1_DIR = "services/sampler/checkpoints"


def diagnosed_files() -> tuple[Path, Path]:
    """The version-1 checkpoint and NN index the diagnosis was written about. They are no longer shipped: on first
    use they are restored from git history (`VERSION_1_COMMIT`) into `$GD2P_CACHE_DIR/models/` (default
    `~/.cache/gd2p/models/`); CoverageError, naming the file, outside a clone that has that commit."""
    import os
    import subprocess

    from shared.atomic import atomic_writer
    from shared.world.objects.cache import CACHE_ENV

    directory = Path(os.environ.get(CACHE_ENV, Path.home() / ".cache" / "gd2p")) / "models" / VERSION_1_COMMIT
    paths = []
    for name in (f"{HAND}_v1.pt", f"{HAND}_v1_nn.npz"):
        path = directory / name
        if not path.is_file():
            spec = f"{VERSION_1_COMMIT}:{VERSION_1_DIR}/{name}"
            try:
                done = subprocess.run(["git", "show", spec], cwd=Path(__file__).resolve().parent.parent,
                                      capture_output=True, timeout=120, check=False)
            except (OSError, subprocess.SubprocessError) as exc:
                done = subprocess.CompletedProcess([], 1, b"", str(exc).encode())
            if done.returncode != 0 or not done.stdout:
                raise CoverageError(f"{name}, the version-1 model this diagnosis was written about, is not shipped and "
                                    f"`git show {spec}` failed ({done.stderr.decode(errors='replace').strip()}): run it "
                                    "in a full clone of the repository")
            directory.mkdir(parents=True, exist_ok=True)
            with atomic_writer(path, "wb") as handle:
                handle.write(done.stdout)
        paths.append(path)
    return paths[0], paths[1]


def run(out: Path, quick: bool = False, workers: int = 2) -> Path:
    """Answer the three questions into `out/sampler-diagnosis/`; returns the report path."""
    from shared.sampling.checkpoint import checkpoint_id
    from shared.sampling.nearest_neighbor import NearestNeighborBaseline
    from shared.sampling.server import SamplerService

    started = time.perf_counter()
    settings = QUICK if quick else FULL
    directory = Path(out) / NAME
    checkpoint, nn_index = diagnosed_files()
    for path in (checkpoint, nn_index):
        if not path.is_file():
            raise CoverageError(f"no version-1 {HAND} checkpoint / index at {path}")
    trained_pool, held_out_pool = checkpoint_objects(checkpoint, nn_index)
    groups = {"trained": pick_objects(trained_pool, settings.trained, seed=settings.selection_seed),
              "held_out": pick_objects(held_out_pool, settings.held_out, seed=settings.selection_seed)}
    objects = groups["trained"] + groups["held_out"]
    donors = bps_donors(groups["trained"], settings.selection_seed)
    coverage = settings.coverage()
    store = ResultStore(directory, {**settings.to_dict(), "objects": groups, "donors": donors,
                                    "checkpoint_id": checkpoint_id(checkpoint), "nn_index": index_fingerprint(nn_index),
                                    "coverage": coverage.to_dict()})

    service = SamplerService({HAND: checkpoint})
    try:
        sampler, index = service.sampler(HAND), NearestNeighborBaseline.load(nn_index)
        encodings = encoding_settings(sampler, index)
        index_frames = frame_placements(index)
        bps = measure_bps(objects, store, sampler, index)
    finally:
        service.close()

    sources: dict[str, PoseSource] = {"diffusion": DiffusionSource(str(checkpoint), "ddpm"), "stored": StoredPosesSource(str(nn_index)),
               "shuffled": ShuffledBpsSource(str(checkpoint), "ddpm", donors=tuple(sorted(donors.items())))}
    results: dict[str, list[dict[str, Any]]] = {}
    with CoveragePool(workers) as pool:
        for key, source in sources.items():
            results[key] = pool.measure(source, groups["trained"] if key == "shuffled" else objects, store, key, coverage,
                                        desc=source.label())

    answers = summary_of(groups, results, bps, encodings, index_frames)
    plot = plot_fractions(groups, results, directory / "validated_fraction.png")
    body = report_body(settings, groups, donors, results, bps, encodings, answers, plot.name)
    summary = {"objects": groups, "donors": donors, "settings": settings.to_dict(), "encodings": encodings, **answers}
    records = [r for rs in results.values() for r in rs] + bps
    return write_experiment(directory, TITLE, body, summary, time.perf_counter() - started, quick, records)


# ----------------------------------------------------------------------------- summary and report
def _in(records: Sequence[dict[str, Any]], objects: Sequence[str]) -> list[dict[str, Any]]:
    wanted = set(objects)
    return [r for r in records if r["object"] in wanted]


def _interval(records: Sequence[dict[str, Any]]) -> Interval:
    return success_interval(pose_trials(records))


def _difference(a: Sequence[dict[str, Any]], b: Sequence[dict[str, Any]]) -> Interval:
    return difference_interval(pose_trials(a), pose_trials(b))


def summary_of(groups: Mapping[str, Sequence[str]], results: Mapping[str, Sequence[dict[str, Any]]],
               bps: Sequence[dict[str, Any]], encodings: Mapping[str, Mapping[str, Any]],
               index_frames: Mapping[str, int]) -> dict[str, Any]:
    """The three answers as figures: validated fractions with intervals, paired differences, BPS agreement."""
    q1 = {}
    for group, objects in groups.items():
        diffusion, stored = _in(results["diffusion"], objects), _in(results["stored"], objects)
        q1[group] = {"objects": len(objects),
                     "diffusion": {**summarize(diffusion), "interval_95": _interval(diffusion).as_dict()},
                     "stored": {**summarize(stored), "interval_95": _interval(stored).as_dict()},
                     "diffusion_minus_stored": _difference(diffusion, stored).as_dict()}
    matched = _in(results["diffusion"], groups["trained"])
    shuffled = results["shuffled"]
    q2 = {"objects": len(shuffled), "shuffled": {**summarize(shuffled), "interval_95": _interval(shuffled).as_dict()},
          "matched": {**summarize(matched), "interval_95": _interval(matched).as_dict()},
          "shuffled_minus_matched": _difference(shuffled, matched).as_dict()}
    q3 = {"settings_agree": settings_agree(encodings), "objects_agree": sum(bps_agree(r) for r in bps), "objects": len(bps),
          "max_train_vs_inference": max(r["train_vs_inference"] for r in bps),
          "max_stored_vs_inference": max(r["stored_vs_inference"] for r in bps),
          "max_moved_vs_inference": max(r["moved_vs_inference"] for r in bps),
          "nn_retrieves_itself": sum(r["nearest_frame"] == r["object"] for r in bps),
          "evaluation_directions_nn_retrieves_itself": sum(d["nearest_frame"] == r["object"] for r in bps for d in r["directions"]),
          "evaluation_directions": sum(len(r["directions"]) for r in bps), "index_frames": dict(index_frames)}
    pushes = sum(r["n_validated"] for rs in results.values() for r in rs)
    seconds = sum(r["seconds"] for rs in results.values() for r in rs)
    return {"question_1": q1, "question_2": q2, "question_3": q3,
            "pushes": pushes, "worker_seconds": round(seconds, 1), "worker_seconds_per_push": round(seconds / pushes, 3) if pushes else None}


def _count(record: Mapping[str, Any] | None) -> str:
    return "–" if record is None else f"{record['fraction_successes']}/{record['fraction_pushed']}"


def _m(value: float) -> str:
    """A BPS difference in metres: 0 when bit-identical, else 2 significant digits or 4 decimals."""
    if value == 0:
        return "0"
    return f"{value:.1e}" if value < 1e-3 else f"{value:.4f}"


def report_body(settings: DiagnosisSettings, groups: Mapping[str, Sequence[str]], donors: Mapping[str, str],
                results: Mapping[str, Sequence[dict[str, Any]]], bps: Sequence[dict[str, Any]],
                encodings: Mapping[str, Mapping[str, Any]], answers: Mapping[str, Any], plot_name: str) -> str:
    by = {key: {r["object"]: r for r in records} for key, records in results.items()}
    q1, q2, q3 = answers["question_1"], answers["question_2"], answers["question_3"]
    group_names = {"trained": "trained on", "held_out": "held out (val loss)"}

    def fraction(entry: Mapping[str, Any]) -> str:
        return str(Interval(**entry["interval_95"]))

    q1_table = markdown_table(
        ["objects", "n", f"diffusion DDPM-100 ({settings.samples} each)", "stored poses", "diffusion − stored (points)"],
        [[group_names[g], q["objects"], fraction(q["diffusion"]), fraction(q["stored"]),
          Interval(**q["diffusion_minus_stored"]).points()] for g, q in q1.items()])
    per_object = markdown_table(
        ["object", "family", "group", "diffusion", "stored", "shuffled BPS", "BPS donor"],
        [[o, family(o), group_names[g], _count(by["diffusion"].get(o)), _count(by["stored"].get(o)),
          _count(by["shuffled"].get(o)), donors.get(o, "–")] for g, objects in groups.items() for o in objects])
    q2_table = markdown_table(
        ["objects (trained on)", "own BPS", "another object's BPS", "shuffled − own (points)"],
        [[q2["objects"], fraction(q2["matched"]), fraction(q2["shuffled"]), Interval(**q2["shuffled_minus_matched"]).points()]])
    q3_settings = markdown_table(
        ["path", "basis (SHA-256 of the points)", "surface samples, seed"],
        [[name, s["basis"], f"{s['surface'][0]}, {s['surface'][1]}"] for name, s in encodings.items()])
    q3_table = markdown_table(
        ["object", "training − inference", "stored (fp16) − inference", "moved − inference", "NN retrieves",
         "own / nearest other (default)", *[f"{d['direction_deg']:g}°: yaw in D, own / nearest other" for d in bps[0]["directions"]]],
        [[r["object"], _m(r["train_vs_inference"]), _m(r["stored_vs_inference"]), _m(r["moved_vs_inference"]),
          r["nearest_frame"], f"{r['distance_to_own']:.3f} / {r['distance_to_nearest_other']:.3f}",
          *[f"{d['object_yaw_in_d_deg']:g}°, {d['distance_to_own']:.3f} / {d['distance_to_nearest_other']:.3f}"
            for d in r["directions"]]] for r in bps])
    return (
        "## The questions\n\n"
        "1. On objects the shipped Allegro checkpoint trained on, how often do diffusion samples (DDPM-100, as "
        "`gd2p sample --validate` draws them) validate in the floating-hand validator, against the same objects' "
        "stored poses (the training dataset's poses of the object, from the shipped NN index)?\n"
        "2. With the BPS shuffled between objects (object A sampled with object B's BPS, validated on A), how much "
        "worse do samples get: does the model use the geometry at all?\n"
        "3. Is the BPS computed in the same frame, scale and point order at inference (the sampler service) as in "
        "training?\n\n"
        f"Objects: {len(groups['trained'])} the checkpoint trained on and {len(groups['held_out'])} of the dataset "
        "it held out for its validation loss, round-robin over families (seeded; the issue's first-look objects "
        f"{' and '.join(FIRST_LOOK_OBJECTS)} first in their families). Each object rests in its default pose at "
        "the origin and is pushed 0.20 m along +x (validator default physics); every sampled pose is pushed. "
        "Intervals: 95%, bootstrap over objects; differences paired by object.\n\n"
        f"## 1. Diffusion samples against stored poses\n\n{q1_table}\n{verdict_1(q1)}\n\n"
        f"## 2. Shuffled BPS\n\n{q2_table}\n{verdict_2(q2)}\n\n"
        f"## 3. The BPS at inference and in training\n\n{verdict_3(q3)}\n\n{q3_settings}\n{q3_table}\n"
        "Max abs difference over the 4096 features (metres). Paths compared: **training** — "
        "`shared.sampling.train` conditions on `shared.sampling.dataset.frame_bps` (the frame's object placed by "
        "`ObjectModel.T_D_O(pose_index, yaw)`, `surface_points(2048, seed 0, T_D_O=...)`, `BasisPointSet().encode`); "
        "**stored** — the NN index's `frame_features` (the same `frame_bps`, saved in float16); **inference** — "
        "`shared.sampling.server.SamplerService.handle`: `object_input(ObjectRef)` then `PoseSampler.encode` "
        "(`ObjectPoints.in_d`: surface samples in O with the checkpoint's count and seed, placed by the request's "
        "`DirectionFrame` through `frame_transform` / `frame_object_transform`, encoded with the checkpoint's basis), "
        "with the object as `gd2p sample` places it; **moved** — the same with the object at "
        f"({MOVED_PLACEMENT[0]}, {MOVED_PLACEMENT[1]}) m turned {MOVED_PLACEMENT[2]:g}° and pushed along "
        f"{MOVED_PLACEMENT[2]:g}° (the same placement in D). The last columns: the object as `gd2p eval methods` places "
        "it (yaw 0 at OBJECT_XY) pushed along each evaluation direction — its yaw in D, and the Euclidean BPS distance "
        "to its own training frame and to the nearest other training frame.\n\n"
        f"## Per object\n\n{per_object}\n![validated fraction per object]({plot_name})\n\n"
        "Stored poses: the object's own frame in `allegro_v1_nn.npz` (built from `data/allegro-train`, the dataset the "
        "checkpoint trained on; the dataset itself is not in the repository); every stored pose is pushed (a seeded "
        f"{settings.samples} when a frame has more), so their count differs per object. "
        f"Cost: {answers['pushes']} pushes, {answers['worker_seconds']:.0f} worker-seconds "
        f"({answers['worker_seconds_per_push']} s per push, sampling included).\n")


def verdict_1(q1: Mapping[str, Any]) -> str:
    trained = q1["trained"]
    gap = Interval(**trained["diffusion_minus_stored"])
    text = (f"On objects it trained on, {trained['diffusion']['pooled_validated_fraction']:.1%} of the model's samples "
            f"validate against {trained['stored']['pooled_validated_fraction']:.1%} of the same objects' stored poses "
            f"({gap.points()} points).")
    if "held_out" in q1 and q1["held_out"]["objects"]:
        held = q1["held_out"]
        text += (f" On dataset objects it held out: {held['diffusion']['pooled_validated_fraction']:.1%} against "
                 f"{held['stored']['pooled_validated_fraction']:.1%}.")
    if gap.high < 0:
        text += " The model does not reproduce its own training data: the gap is the model's, not only the data's."
    elif gap.low > 0:
        text += " The model's samples validate more often than the stored poses."
    else:
        text += " The interval includes no difference."
    return text


def verdict_2(q2: Mapping[str, Any]) -> str:
    drop = Interval(**q2["shuffled_minus_matched"])
    text = (f"Conditioned on another object's BPS, {q2['shuffled']['pooled_validated_fraction']:.1%} of the samples "
            f"validate against {q2['matched']['pooled_validated_fraction']:.1%} with the object's own ({drop.points()} points).")
    if drop.high < 0:
        return text + " The model uses the geometry: samples made for another object fail more often."
    return (text + " The interval includes no loss: these objects do not show that the model's samples depend on the "
            "geometry they are conditioned on.")


def verdict_3(q3: Mapping[str, Any]) -> str:
    same = q3["settings_agree"] and q3["objects_agree"] == q3["objects"]
    text = (f"Basis and surface samples {'agree' if q3['settings_agree'] else '**differ**'} across the three paths; "
            f"{q3['objects_agree']} of {q3['objects']} objects get the same BPS at inference as in training (max "
            f"|training − inference| {_m(q3['max_train_vs_inference'])} m, stored float16 − inference "
            f"{_m(q3['max_stored_vs_inference'])} m, moved − inference {_m(q3['max_moved_vs_inference'])} m), and the NN "
            f"index retrieves the object itself for {q3['nn_retrieves_itself']} of {q3['objects']}. ")
    text += ("Same frame, scale and point order: the inference BPS is not where the gap comes from. " if same
             else "**The paths disagree**: see the table. ")
    frames = q3["index_frames"]
    return text + (f"But as `gd2p eval methods` places objects (yaw 0, pushed along 60°, 180°, 300°), the object stands "
                   f"turned in D, while {frames['default_placement']} of the dataset's {frames['frames']} frames are the "
                   "default resting pose at yaw 0: for those placements the NN index retrieves the object itself in "
                   f"{q3['evaluation_directions_nn_retrieves_itself']} of {q3['evaluation_directions']} (a turned object "
                   "that is not symmetric about z is farther in BPS from its own training frame than other objects are).")


def plot_fractions(groups: Mapping[str, Sequence[str]], results: Mapping[str, Sequence[dict[str, Any]]], path: Path) -> Path:
    """Validated fraction per object: diffusion, stored poses, shuffled BPS side by side."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    objects = [o for members in groups.values() for o in members]
    by = {key: {r["object"]: r["validated_fraction"] for r in records} for key, records in results.items()}
    figure, axis = plt.subplots(figsize=(max(6.0, 0.55 * len(objects) + 2), 4), dpi=110)
    width = 0.27
    for offset, (key, label) in enumerate((("diffusion", "diffusion (own BPS)"), ("stored", "stored poses"),
                                           ("shuffled", "diffusion (another object's BPS)"))):
        xs = [i + (offset - 1) * width for i, o in enumerate(objects) if o in by[key]]
        axis.bar(xs, [by[key][o] for o in objects if o in by[key]], width, label=label)
    if groups["held_out"]:
        axis.axvline(len(groups["trained"]) - 0.5, color="gray", linestyle=":")
    axis.set_xticks(range(len(objects)), objects, rotation=60, ha="right", fontsize=8)
    axis.set_ylim(0, 1.05)
    axis.set_ylabel("validated fraction")
    axis.set_title("trained on | held out (right of the dotted line)", fontsize=9)
    axis.legend(fontsize=8)
    axis.grid(True, axis="y", alpha=0.3)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)
    return path

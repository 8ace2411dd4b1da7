"""The paper's Nearest Neighbor baseline: retrieve the stored poses of the most similar training object.

"Given a test object, we find the training object with the most similar BPS representation (in
terms of Euclidean distance) and retrieve its associated hand poses." Here the unit of retrieval is
a training *frame* — one placement (resting pose, yaw) of a training object in D, see dataset.py —
because a stored pose is only meaningful relative to the placement it was validated in; an object
stored in one placement is exactly the paper's case.

The index holds the BPS of every training frame (same basis as the sampler, so a checkpoint's
`bps` can be passed) and the poses of each frame. It can be saved to / loaded from one .npz file,
so evaluation does not need the Parquet store or the objects' meshes.

`build_index` (`gd2p sampler-nn build`) writes such a file with a manifest beside it; the sampler
service serves it as `sampler="nearest"` through `NearestNeighborSampler`, which places the query
object in D and samples its surface exactly as the diffusion path does (`sampling.ObjectPoints`).
The shipped indexes live beside the shipped checkpoints: `checkpoints/<hand>_nn.npz`.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from shared.contracts.messages import DirectionFrame
from shared.frames import poses_d_to_world
from shared.sampling.capture_bps import FrameCaptures, capture_store_spec, load_captures
from shared.sampling.checkpoint import SHIPPED_DIR, checkpoint_id, verify_file, write_manifest
from shared.sampling.dataset import SURFACE_POINTS, SURFACE_SEED, Frame, PoseDataset, frame_bps, load_pose_dataset
from shared.sampling.sampling import ObjectInput, ObjectPoints, SampleResult, SamplerInputError, check_count_and_seed
from shared.world.bps import BasisPointSet, BPSError
from shared.world.objects.cache import save_npz

INDEX_FORMAT = "gd2p-nn-v1"
NN_INDEX_ENV = "GD2P_SAMPLER_NN_INDEX_{hand}"  # e.g. GD2P_SAMPLER_NN_INDEX_ALLEGRO=/path/to/allegro_nn.npz


class NearestNeighborError(ValueError):
    """An empty or malformed index, or a query that does not match its basis."""


@dataclass
class NeighborMatch:
    """The nearest training frame to a query and its stored poses (in D)."""

    object_id: str
    frame: Frame
    distance: float  # Euclidean distance between the BPS vectors
    poses: np.ndarray  # [m, 25] float64 — all of the frame's poses, or a seeded subset of k


class NearestNeighborBaseline:
    """BPS nearest-neighbour retrieval over the training frames of one hand."""

    def __init__(self, hand: str, bps: BasisPointSet, frames: list[Frame], frame_features: np.ndarray,
                 poses: np.ndarray, frame_index: np.ndarray, surface_points: int = SURFACE_POINTS,
                 surface_seed: int = SURFACE_SEED, manifest: dict[str, Any] | None = None):
        frame_features = np.asarray(frame_features, dtype=np.float32)
        if not frames or frame_features.shape != (len(frames), bps.n):
            raise NearestNeighborError(f"index needs one {bps.n}-d BPS per frame; got {frame_features.shape} for {len(frames)} frames")
        self.hand, self.bps, self.frames = hand, bps, frames
        # How each frame's surface was sampled for its BPS; a query must be sampled the same way.
        self.surface_points, self.surface_seed = int(surface_points), int(surface_seed)
        self.manifest: dict[str, Any] = dict(manifest or {})
        self.frame_features = frame_features
        self._squared_norms = (frame_features.astype(np.float64) ** 2).sum(axis=1)
        order = np.argsort(frame_index, kind="stable")
        self._poses = np.asarray(poses, dtype=np.float64)[order]
        self._starts = np.searchsorted(np.asarray(frame_index)[order], np.arange(len(frames) + 1))

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def pose_count(self) -> int:
        return len(self._poses)

    @property
    def poses(self) -> np.ndarray:
        """[P, 25] every stored pose (in D), grouped by frame; read-only."""
        view = self._poses.view()
        view.flags.writeable = False
        return np.asarray(view)

    @classmethod
    def from_dataset(cls, dataset: PoseDataset, bps: BasisPointSet | None = None, progress: bool = False,
                     captures: FrameCaptures | None = None) -> NearestNeighborBaseline:
        """The frames' mesh BPS as keys; with `captures`, also every reconstructed capture of a frame as a key of
        its own, holding the frame's poses moved into that capture's frame (the data a capture-trained sampler has)."""
        bps = bps or BasisPointSet()
        features = frame_bps(dataset.frames, bps, SURFACE_POINTS, SURFACE_SEED, progress=progress)
        frames, poses, frame_index = dataset.frames, dataset.poses, dataset.frame_index
        if captures is not None:
            frames, features, poses, frame_index = _with_capture_keys(dataset, features, captures)
        return cls(dataset.hand, bps, frames, features, poses, frame_index, SURFACE_POINTS, SURFACE_SEED)

    @classmethod
    def from_directory(cls, directory: str | Path, hand: str, bps: BasisPointSet | None = None,
                       progress: bool = False) -> NearestNeighborBaseline:
        return cls.from_dataset(load_pose_dataset(directory, hand), bps, progress)

    # ------------------------------------------------------------------ queries
    def _squared_distances(self, features: np.ndarray) -> np.ndarray:
        """[frames] squared Euclidean BPS distance of every training frame to a query BPS vector."""
        query = np.asarray(features, dtype=np.float64).reshape(-1)
        if query.shape != (self.bps.n,):
            raise NearestNeighborError(f"query BPS must have {self.bps.n} values, got {query.size}")
        return np.asarray(self._squared_norms - 2.0 * (self.frame_features @ query) + query @ query)

    def nearest(self, features: np.ndarray) -> tuple[int, float]:
        """(row of the nearest training frame, Euclidean BPS distance) for a query BPS vector."""
        squared = self._squared_distances(features)
        row = int(np.argmin(squared))
        return row, float(np.sqrt(max(squared[row], 0.0)))

    def nearest_frames_poses(self, features: np.ndarray, k: int) -> np.ndarray:
        """[<= k, 25] the stored poses of the nearest frames, nearest first, until there are `k`.

        Retrieval given the same number of candidates as the model's K samples (one frame holds
        typically 20-90 poses): every pose of the nearest frame, then of the next nearest, and so on;
        the last frame contributes its first poses in stored order.
        """
        if k < 1:
            raise NearestNeighborError(f"k must be >= 1, got {k}")
        counts = np.diff(self._starts)
        order = np.argsort(self._squared_distances(features), kind="stable")
        needed = int(np.searchsorted(np.cumsum(counts[order]), k)) + 1
        rows = order[:needed]
        return np.asarray(np.concatenate([self._poses[self._starts[r]:self._starts[r + 1]] for r in rows])[:k].copy())

    def query(self, features: np.ndarray, k: int | None = None, seed: int = 0) -> NeighborMatch:
        """The nearest frame's poses: all of them, or a seeded random subset of `k` when it has more."""
        row, distance = self.nearest(features)
        return NeighborMatch(self.frames[row].object_id, self.frames[row], distance, self.frame_poses(row, k, seed))

    def frame_row(self, frame: Frame) -> int:
        """The row of a training frame (object, resting pose, yaw); NearestNeighborError when it is not indexed."""
        key = (frame.object_id, frame.pose_index, round(frame.yaw_rad, 6))
        for row, indexed in enumerate(self.frames):
            if (indexed.object_id, indexed.pose_index, round(indexed.yaw_rad, 6)) == key:
                return row
        raise NearestNeighborError(f"{frame} is not a frame of this index")

    def frame_poses(self, row: int, k: int | None = None, seed: int = 0) -> np.ndarray:
        """[m, 25] the stored poses (in D) of the frame at `row`: all, or a seeded random subset of `k` when it has more."""
        poses = self._poses[self._starts[row]:self._starts[row + 1]]
        if k is not None and k < len(poses):
            poses = poses[np.sort(np.random.default_rng(seed).choice(len(poses), size=k, replace=False))]
        return np.asarray(poses.copy())

    def query_points(self, points_d: np.ndarray, k: int | None = None, seed: int = 0) -> NeighborMatch:
        """Like `query`, for object surface points in D (encoded with this index's basis)."""
        try:
            features = self.bps.encode(points_d)
        except BPSError as exc:
            raise NearestNeighborError(str(exc)) from exc
        return self.query(features, k, seed)

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | Path, half: bool = False) -> Path:
        """One .npz with the basis, the frames' BPS (float16 with `half`) and every pose (no pickles)."""
        frame_rows = np.repeat(np.arange(len(self.frames)), np.diff(self._starts))
        return save_npz(
            Path(path), format=np.array(INDEX_FORMAT), hand=np.array(self.hand),
            basis=self.bps.basis.astype(np.float32), bps_meta=np.array([self.bps.n, self.bps.radius, self.bps.seed]),
            surface_meta=np.array([self.surface_points, self.surface_seed], dtype=np.int64),
            manifest=np.array(json.dumps(self.manifest, sort_keys=True)),
            frame_object_ids=np.array([f.object_id for f in self.frames]),
            frame_pose_index=np.array([f.pose_index for f in self.frames], dtype=np.int64),
            frame_yaw_rad=np.array([f.yaw_rad for f in self.frames]),
            frame_features=self.frame_features.astype(np.float16 if half else np.float32),
            poses=self._poses, frame_index=frame_rows)

    @classmethod
    def load(cls, path: str | Path) -> NearestNeighborBaseline:
        try:
            with np.load(Path(path), allow_pickle=False) as data:
                arrays = {name: data[name] for name in data.files}
        except (OSError, ValueError) as exc:
            raise NearestNeighborError(f"{path}: unreadable nearest-neighbour index: {exc}") from exc
        if str(arrays.get("format", "")) != INDEX_FORMAT:
            raise NearestNeighborError(f"{path}: not a nearest-neighbour index ({INDEX_FORMAT})")
        verify_file(path, NearestNeighborError)
        n, radius, seed = arrays["bps_meta"]
        bps = BasisPointSet.from_dict({"n": int(n), "radius": float(radius), "seed": int(seed), "basis": arrays["basis"]})
        frames = [Frame(str(o), int(i), float(y)) for o, i, y in
                  zip(arrays["frame_object_ids"], arrays["frame_pose_index"], arrays["frame_yaw_rad"], strict=True)]
        # Indexes written before these fields existed were built with the dataset module's defaults.
        surface_points, surface_seed = arrays.get("surface_meta", np.array([SURFACE_POINTS, SURFACE_SEED])).tolist()
        manifest = json.loads(str(arrays["manifest"])) if "manifest" in arrays else {}
        return cls(str(arrays["hand"]), bps, frames, arrays["frame_features"], arrays["poses"], arrays["frame_index"],
                   surface_points, surface_seed, manifest)


def _with_capture_keys(dataset: PoseDataset, features: np.ndarray, captures: FrameCaptures
                       ) -> tuple[list[Frame], np.ndarray, np.ndarray, np.ndarray]:
    """Frames, keys, poses and pose rows with a row added per reconstructed capture of a captured frame."""
    row_of = {frame: i for i, frame in enumerate(captures.frames)}
    frames, keys = list(dataset.frames), [features]
    poses, frame_index = [dataset.poses], [dataset.frame_index]
    for row, frame in enumerate(dataset.frames):
        if frame not in row_of:
            continue
        mine = dataset.poses[dataset.frame_index == row]
        captured = row_of[frame]
        for variant in np.flatnonzero(captures.ok[captured]):
            moved = mine.copy()
            moved[:, :2] += captures.shift_xy[captured, variant]
            poses.append(moved)
            frame_index.append(np.full(len(mine), len(frames), dtype=np.int64))
            keys.append(captures.bps[captured, variant][None])
            frames.append(frame)
    return frames, np.concatenate(keys), np.concatenate(poses), np.concatenate(frame_index)


# ----------------------------------------------------------------------------- building a shipped index
def default_nn_index_path(hand: str) -> Path:
    """Where the sampler looks for `hand`'s index: $GD2P_SAMPLER_NN_INDEX_<HAND>, else the shipped file."""
    override = os.environ.get(NN_INDEX_ENV.format(hand=hand.upper()))
    return Path(override).expanduser() if override else SHIPPED_DIR / f"{hand}_nn.npz"


def half_precision_agreement(frame_features: np.ndarray) -> dict[str, Any]:
    """Does storing the frames' BPS in float16 change what is retrieved?

    Every training frame is queried with its float32 BPS against a float16 and a float32 copy of the
    index: `top1_agreement` compares the nearest frame (itself, barring duplicates),
    `leave_one_out_top1_agreement` the nearest *other* frame — what an unseen object close to that
    frame would get. Both are fractions of frames; None when there is a single frame.
    """
    query = np.asarray(frame_features, dtype=np.float32).astype(np.float64)
    half = np.asarray(frame_features, dtype=np.float32).astype(np.float16).astype(np.float64)

    def squared_distances(index: np.ndarray) -> np.ndarray:  # [query, frame]
        return np.asarray((index ** 2).sum(1)[None] - 2.0 * query @ index.T + (query ** 2).sum(1)[:, None])

    full_d, half_d = squared_distances(query), squared_distances(half)
    top1 = float(np.mean(full_d.argmin(1) == half_d.argmin(1)))
    if len(query) < 2:
        return {"frames": len(query), "top1_agreement": top1, "leave_one_out_top1_agreement": None}
    np.fill_diagonal(full_d, np.inf)
    np.fill_diagonal(half_d, np.inf)
    leave_one_out = float(np.mean(full_d.argmin(1) == half_d.argmin(1)))
    return {"frames": len(query), "top1_agreement": top1, "leave_one_out_top1_agreement": leave_one_out}


def build_index(dataset_dir: str | Path, hand: str, out: str | Path, half: bool = False, command: str = "",
                progress: bool = False, captures: str | Path | None = None) -> NearestNeighborBaseline:
    """Index every training frame of `hand` in a dataset store; write `out` and `<out>.manifest.json`.
    `captures`: a finished capture store (shared/sampling/capture_bps.py) whose captures are added as keys.

    With `half` the frames' BPS are stored in float16, but only if that changes no frame's nearest
    neighbour (see `half_precision_agreement`); NearestNeighborError otherwise.
    """
    started = time.perf_counter()
    dataset = load_pose_dataset(dataset_dir, hand)
    frame_captures = None if captures is None else load_captures(captures)
    index = NearestNeighborBaseline.from_dataset(dataset, progress=progress, captures=frame_captures)
    manifest: dict[str, Any] = {
        "format": INDEX_FORMAT, "hand": hand, "command": command,
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "dataset": {"path": str(dataset_dir), "sha256": dataset.fingerprint, "objects": len(dataset.objects()),
                    "frames": len(dataset.frames), "poses_total": len(dataset),
                    "frames_skipped": dataset.skipped_summary()},
        "bps": {"n": index.bps.n, "radius": index.bps.radius, "seed": index.bps.seed},
        "surface": {"points": index.surface_points, "seed": index.surface_seed},
        "features_dtype": "float16" if half else "float32",
    }
    if captures is not None:
        manifest["captures"] = {**capture_store_spec(captures), "keys": len(index) - len(dataset.frames)}
    if half:
        agreement = half_precision_agreement(index.frame_features)
        if agreement["top1_agreement"] < 1.0 or (agreement["leave_one_out_top1_agreement"] or 1.0) < 1.0:
            raise NearestNeighborError(f"float16 BPS features would change retrieval ({agreement}); build without --half")
        manifest["float16_check"] = agreement
    manifest["wall_time_s"] = round(time.perf_counter() - started, 1)
    index.manifest = manifest
    path = index.save(out, half=half)
    write_manifest(path, manifest)
    return NearestNeighborBaseline.load(path)  # what the sampler will serve (float16 features if `half`)


# ----------------------------------------------------------------------------- serving
@dataclass
class NearestSample:
    """A nearest-neighbour reply: the retrieved poses (in D and world, as a SampleResult) and the match."""

    result: SampleResult
    match: NeighborMatch
    source_id: str  # names the index file and the matched training object


@dataclass
class NearestNeighborSampler:
    """The index served like a sampler: an object in a DirectionFrame -> the nearest frame's poses.

    The object's surface points are sampled and placed in D exactly as `PoseSampler` does (same
    `ObjectPoints`, with the sample count and seed the index was built with), then encoded with the
    index's basis. Thread-safe: queries only read the index.
    """

    index: NearestNeighborBaseline
    index_id: str = "nn:in-memory"
    _objects: ObjectPoints = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._objects = ObjectPoints(self.index.surface_points, self.index.surface_seed)

    @property
    def hand(self) -> str:
        return self.index.hand

    @classmethod
    def load(cls, path: str | Path) -> NearestNeighborSampler:
        """Serve an index file; its id is `nn:<file name>@<first 8 hex of its SHA-256>`."""
        path = Path(path)
        if not path.is_file():
            raise NearestNeighborError(f"{path}: no such nearest-neighbour index")
        return cls(NearestNeighborBaseline.load(path), f"nn:{path.name}@{checkpoint_id(path)[:8]}")

    def points_in_d(self, obj: ObjectInput, frame: DirectionFrame | None = None) -> tuple[np.ndarray, np.ndarray, str]:
        """(the object's surface points in D [N, 3] as the index encodes them, T_world_D, a label naming the object)."""
        return self._objects.in_d(obj, frame)

    def sample(self, obj: ObjectInput, frame: DirectionFrame | None = None, k: int = 200, seed: int = 0) -> NearestSample:
        """The nearest training frame's poses for `obj` in `frame`: a seeded subset of `k`, or all when it has fewer."""
        started = time.perf_counter()
        check_count_and_seed(k, seed)
        points_d, T_world_D, label = self.points_in_d(obj, frame)
        try:
            match = self.index.query_points(points_d, k=k, seed=seed)
        except NearestNeighborError as exc:
            raise SamplerInputError(f"{label}: {exc}") from exc
        result = SampleResult(match.poses, poses_d_to_world(match.poses, T_world_D), T_world_D,
                              time.perf_counter() - started, "nearest", 0, label)
        return NearestSample(result, match, f"{self.index_id}:{match.object_id}")

"""The paper's Nearest Neighbor baseline: retrieve the stored poses of the most similar training object.

"Given a test object, we find the training object with the most similar BPS representation (in
terms of Euclidean distance) and retrieve its associated hand poses." Here the unit of retrieval is
a training *frame* — one placement (resting pose, yaw) of a training object in D, see dataset.py —
because a stored pose is only meaningful relative to the placement it was validated in; an object
stored in one placement is exactly the paper's case.

The index holds the BPS of every training frame (same basis as the sampler, so a checkpoint's
`bps` can be passed) and the poses of each frame. It can be saved to / loaded from one .npz file,
so evaluation does not need the Parquet store or the objects' meshes.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.sampler.dataset import Frame, PoseDataset, frame_bps, load_pose_dataset
from shared.bps import BasisPointSet, BPSError
from shared.objects.cache import save_npz

INDEX_FORMAT = "gd2p-nn-v1"


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
                 poses: np.ndarray, frame_index: np.ndarray):
        frame_features = np.asarray(frame_features, dtype=np.float32)
        if not frames or frame_features.shape != (len(frames), bps.n):
            raise NearestNeighborError(f"index needs one {bps.n}-d BPS per frame; got {frame_features.shape} for {len(frames)} frames")
        self.hand, self.bps, self.frames = hand, bps, frames
        self.frame_features = frame_features
        self._squared_norms = (frame_features.astype(np.float64) ** 2).sum(axis=1)
        order = np.argsort(frame_index, kind="stable")
        self._poses = np.asarray(poses, dtype=np.float64)[order]
        self._starts = np.searchsorted(np.asarray(frame_index)[order], np.arange(len(frames) + 1))

    def __len__(self) -> int:
        return len(self.frames)

    @classmethod
    def from_dataset(cls, dataset: PoseDataset, bps: BasisPointSet | None = None, progress: bool = False) -> "NearestNeighborBaseline":
        bps = bps or BasisPointSet()
        features = frame_bps(dataset.frames, bps, progress=progress)
        return cls(dataset.hand, bps, dataset.frames, features, dataset.poses, dataset.frame_index)

    @classmethod
    def from_directory(cls, directory: str | Path, hand: str, bps: BasisPointSet | None = None,
                       progress: bool = False) -> "NearestNeighborBaseline":
        return cls.from_dataset(load_pose_dataset(directory, hand), bps, progress)

    # ------------------------------------------------------------------ queries
    def nearest(self, features: np.ndarray) -> tuple[int, float]:
        """(row of the nearest training frame, Euclidean BPS distance) for a query BPS vector."""
        query = np.asarray(features, dtype=np.float64).reshape(-1)
        if query.shape != (self.bps.n,):
            raise NearestNeighborError(f"query BPS must have {self.bps.n} values, got {query.size}")
        squared = self._squared_norms - 2.0 * (self.frame_features @ query) + query @ query
        row = int(np.argmin(squared))
        return row, float(np.sqrt(max(squared[row], 0.0)))

    def query(self, features: np.ndarray, k: int | None = None, seed: int = 0) -> NeighborMatch:
        """The nearest frame's poses: all of them, or a seeded random subset of `k` when it has more."""
        row, distance = self.nearest(features)
        poses = self._poses[self._starts[row]:self._starts[row + 1]]
        if k is not None and k < len(poses):
            poses = poses[np.sort(np.random.default_rng(seed).choice(len(poses), size=k, replace=False))]
        return NeighborMatch(self.frames[row].object_id, self.frames[row], distance, poses.copy())

    def query_points(self, points_d: np.ndarray, k: int | None = None, seed: int = 0) -> NeighborMatch:
        """Like `query`, for object surface points in D (encoded with this index's basis)."""
        try:
            features = self.bps.encode(points_d)
        except BPSError as exc:
            raise NearestNeighborError(str(exc)) from exc
        return self.query(features, k, seed)

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | Path) -> Path:
        """One .npz with the basis, the frames' BPS and every pose (no pickles)."""
        frame_rows = np.repeat(np.arange(len(self.frames)), np.diff(self._starts))
        return save_npz(
            Path(path), format=np.array(INDEX_FORMAT), hand=np.array(self.hand),
            basis=self.bps.basis.astype(np.float32), bps_meta=np.array([self.bps.n, self.bps.radius, self.bps.seed]),
            frame_object_ids=np.array([f.object_id for f in self.frames]),
            frame_pose_index=np.array([f.pose_index for f in self.frames], dtype=np.int64),
            frame_yaw_rad=np.array([f.yaw_rad for f in self.frames]),
            frame_features=self.frame_features, poses=self._poses, frame_index=frame_rows)

    @classmethod
    def load(cls, path: str | Path) -> "NearestNeighborBaseline":
        try:
            with np.load(Path(path), allow_pickle=False) as data:
                arrays = {name: data[name] for name in data.files}
        except (OSError, ValueError) as exc:
            raise NearestNeighborError(f"{path}: unreadable nearest-neighbour index: {exc}") from exc
        if str(arrays.get("format", "")) != INDEX_FORMAT:
            raise NearestNeighborError(f"{path}: not a nearest-neighbour index ({INDEX_FORMAT})")
        n, radius, seed = arrays["bps_meta"]
        bps = BasisPointSet.from_dict({"n": int(n), "radius": float(radius), "seed": int(seed), "basis": arrays["basis"]})
        frames = [Frame(str(o), int(i), float(y)) for o, i, y in
                  zip(arrays["frame_object_ids"], arrays["frame_pose_index"], arrays["frame_yaw_rad"])]
        return cls(str(arrays["hand"]), bps, frames, arrays["frame_features"], arrays["poses"], arrays["frame_index"])

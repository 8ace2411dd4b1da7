"""Reading the data engine's pose store for training, and the BPS of each training frame.

The store (`shared.data.dataset_store`: Parquet shards listed in a `manifest.json` with their checksums)
is opened and verified through `DatasetStore`, the one reader of its layout: a shard that is
missing, modified or not in the manifest is never read, and only successful pushes are read (a
version-2 store keeps its failures beside them; `DatasetStore.rows` leaves them out) unless a model
that learns from failures asks for them too (`load_pose_dataset(with_failures=True)`). Columns used here:

    object_id   string            library id (or `mesh-<hash>` of a mesh loaded on this machine)
    hand        string            "allegro" | "leap"
    pose        list<float>[25]   [p(3), r6(6), q(16)] of the hand base in D (push along +x)
    pose_index  int, optional     which resting pose of the object (null / absent: its default pose)
    yaw_rad     float, optional   the object's yaw about D's z axis (null / absent: 0)

Other columns (metrics, provenance) are ignored.

Frame convention (the choice this module makes, docs/architecture.md §Frames): a stored pose is in the direction
frame D of its push — origin at the object's centre of mass projected onto the table, +x the
push direction — with the object resting in `pose_index`, turned by `yaw_rad` about z, exactly as
the generator and validator placed it (`ObjectModel.T_D_O(pose_index, yaw_rad)`). So the BPS a
pose is trained with is the BPS of *that* placement of the object in D; nothing is rotated. Poses
sharing (object, resting pose, yaw) share one "frame" and one BPS, computed once.
"""
from __future__ import annotations

import hashlib
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from numpy.typing import DTypeLike
from tqdm import tqdm

from shared.data.dataset_store import SUCCESS_COLUMN, DatasetStore, StoreError, succeeded
from shared.frames import POSE_DIM
from shared.world.bps import BasisPointSet, BPSError
from shared.world.objects import ObjectLoadError, load_object, split_of
from shared.world.objects.catalog import library_ids

REQUIRED_COLUMNS = ("object_id", "hand", "pose")
OPTIONAL_COLUMNS = ("pose_index", "yaw_rad")
DEFAULT_POSE_INDEX = -1  # "the object's default resting pose"
SURFACE_POINTS = 2048  # object surface samples behind each BPS
SURFACE_SEED = 0
_YAW_DECIMALS = 6  # yaws equal to a micro-radian are one frame


class DatasetError(ValueError):
    """A pose store that cannot be used for training (missing, malformed, wrong hand, test objects)."""


@dataclass(frozen=True)
class Frame:
    """One placement of one object in D: all poses recorded against it share its BPS."""

    object_id: str
    pose_index: int  # DEFAULT_POSE_INDEX: the object's default resting pose
    yaw_rad: float


@dataclass
class PoseDataset:
    """Poses of one hand, each pointing at the frame (object placement) it was validated in."""

    hand: str
    poses: np.ndarray  # [N, 25] float32, in D
    frame_index: np.ndarray  # [N] int64 into `frames`
    frames: list[Frame]
    fingerprint: str  # content hash of the shards read (see dataset_fingerprint)
    # Frames of the store left out, with their poses: their resting pose does not exist on this machine
    # (`unplaceable_frames`); (frame, poses) pairs, recorded in what is built from the dataset.
    skipped: list[tuple[Frame, int]] = field(default_factory=list)
    # [N] bool: the pose is a failed push (read only when asked, `load_pose_dataset(with_failures=True)`);
    # None: every pose succeeded.
    failed: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def object_ids(self) -> np.ndarray:
        """[N] the object id of every pose."""
        return np.array([self.frames[i].object_id for i in self.frame_index], dtype=object)

    def objects(self) -> list[str]:
        return sorted({f.object_id for f in self.frames})

    def subset(self, keep_objects: set[str] | list[str]) -> PoseDataset:
        """The poses of `keep_objects` only (frames renumbered)."""
        keep = set(keep_objects)
        return self.with_frames([i for i, f in enumerate(self.frames) if f.object_id in keep],
                                [(f, n) for f, n in self.skipped if f.object_id in keep])

    def with_frames(self, kept_frames: list[int], skipped: list[tuple[Frame, int]]) -> PoseDataset:
        """The poses of the frames `kept_frames` (indices, renumbered in that order) only; `skipped` recorded."""
        renumber = np.full(len(self.frames), -1, dtype=np.int64)
        renumber[kept_frames] = np.arange(len(kept_frames))
        rows = renumber[self.frame_index] >= 0
        return PoseDataset(self.hand, self.poses[rows], renumber[self.frame_index[rows]],
                           [self.frames[i] for i in kept_frames], self.fingerprint, skipped,
                           None if self.failed is None else self.failed[rows])

    def successes(self) -> PoseDataset:
        """The successful pushes only (frames kept, even one left without a pose)."""
        if self.failed is None:
            return self
        keep = ~self.failed
        return PoseDataset(self.hand, self.poses[keep], self.frame_index[keep], self.frames, self.fingerprint,
                           self.skipped)

    def skipped_summary(self) -> list[dict[str, Any]]:
        """The skipped frames for a manifest: object, resting pose, yaw and how many poses each held."""
        return [{"object_id": f.object_id, "pose_index": f.pose_index, "yaw_rad": f.yaw_rad, "poses": n}
                for f, n in self.skipped]


# ----------------------------------------------------------------------------- reading
def open_store(directory: str | Path) -> DatasetStore:
    """The pose store in `directory`, its shards checked against the manifest (DatasetError if not)."""
    directory = Path(directory)
    if not directory.is_dir():
        raise DatasetError(f"{directory}: no such dataset directory")
    try:
        store = DatasetStore.open(directory)
        store.verify()
    except StoreError as exc:
        raise DatasetError(f"{exc} (build a store with `gd2p dataset build`)") from exc
    return store


def dataset_fingerprint(store: DatasetStore) -> str:
    """SHA-256 over the shards' relative names and bytes: equal iff the stored data (failures too) is equal."""
    digest = hashlib.sha256()
    for path in store.shard_paths():
        digest.update(str(path.relative_to(store.directory)).encode() + b"\0")
        with path.open("rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def load_pose_dataset(directory: str | Path, hand: str, with_failures: bool = False) -> PoseDataset:
    """All successful poses of `hand` in the store, grouped into frames, and its failed pushes too (marked in
    `failed`) when `with_failures`. Refuses test-split library objects."""
    directory = Path(directory)
    store = open_store(directory)
    if not store.shard_paths():
        raise DatasetError(f"{directory}: the store holds no poses yet")
    table = _read_rows(store, with_failures)
    rows = pc.fill_null(pc.equal(table.column("hand"), hand), False)
    if not pc.any(rows).as_py():
        present = sorted(h for h in pc.unique(table.column("hand")).to_pylist() if h is not None)
        raise DatasetError(f"{directory}: no poses for hand {hand!r} (hands present: {present})")
    table = table.filter(rows)
    object_ids = table.column("object_id").to_pylist()
    _refuse_test_objects(object_ids, directory)
    poses = _pose_matrix(table, directory)
    pose_index = _optional_column(table, "pose_index", DEFAULT_POSE_INDEX, np.int64)
    yaw = np.round(_optional_column(table, "yaw_rad", 0.0, np.float64), _YAW_DECIMALS)
    frames, frame_index = _group_frames(object_ids, pose_index, yaw)
    failed = pc.invert(succeeded(table)).to_numpy(zero_copy_only=False).astype(bool) if with_failures else None
    dataset = PoseDataset(hand, poses, frame_index, frames, dataset_fingerprint(store), failed=failed)
    return _without_frames(dataset, unplaceable_frames(frames), directory)


def unplaceable_frames(frames: list[Frame]) -> list[Frame]:
    """The frames whose resting pose the object does not have on this machine.

    Resting poses are trimesh's stable poses of the object's hull, most probable first. Where several are
    equally probable, or a facet's sliver triangles make its area NaN, which ones make the list and in
    what order can differ between machines (CPU, library builds): a store built elsewhere can name a pose
    index this machine does not have (1 frame of the 1,129 of datasets/allegro-v2 on the VM of 2026-12-03).
    Such frames cannot be placed as they were validated, so they are left out, never placed otherwise.
    """
    unplaceable = []
    for frame in frames:
        if frame.pose_index == DEFAULT_POSE_INDEX:
            continue
        try:
            count = len(load_object(frame.object_id).resting_poses)
        except ObjectLoadError:
            continue  # frame_bps reports an object that does not load
        if not 0 <= frame.pose_index < count:
            unplaceable.append(frame)
    return unplaceable


def _without_frames(dataset: PoseDataset, dropped: list[Frame], directory: Path) -> PoseDataset:
    """`dataset` without the poses of `dropped` frames (recorded in `skipped`), with a warning naming them."""
    if not dropped:
        return dataset
    counts = np.bincount(dataset.frame_index, minlength=len(dataset.frames))
    index = {frame: i for i, frame in enumerate(dataset.frames)}
    skipped = [(frame, int(counts[index[frame]])) for frame in dropped]
    names = ", ".join(f"{f.object_id} resting pose {f.pose_index} ({n} poses)" for f, n in skipped)
    warnings.warn(f"{directory}: {len(skipped)} frame(s) left out, their resting pose does not exist on this "
                  f"machine: {names}", stacklevel=3)
    drop = {index[f] for f in dropped}
    return dataset.with_frames([i for i in range(len(dataset.frames)) if i not in drop], dataset.skipped + skipped)


def _read_rows(store: DatasetStore, with_failures: bool) -> pa.Table:
    """The store's successful rows, and its failed ones when `with_failures` (read by the store, the one reader
    of its shards), in the columns training uses: the outcome column only when it tells rows apart."""
    try:
        table = store.rows(outcome="all" if with_failures else "success")
    except (OSError, pa.ArrowException) as exc:
        raise DatasetError(f"{store.directory}: a shard is not readable Parquet: {exc}") from exc
    missing = [c for c in REQUIRED_COLUMNS if c not in table.column_names]
    if missing:
        raise DatasetError(f"{store.directory}: missing column(s) {missing}; a shard needs {list(REQUIRED_COLUMNS)}")
    wanted = REQUIRED_COLUMNS + OPTIONAL_COLUMNS + ((SUCCESS_COLUMN,) if with_failures else ())
    return table.select([c for c in wanted if c in table.column_names])


def _pose_matrix(table: pa.Table, directory: Path) -> np.ndarray:
    column = table.column("pose").combine_chunks()
    if column.null_count:
        raise DatasetError(f"{directory}: {column.null_count} row(s) have no pose")
    lengths = column.value_lengths().to_numpy(zero_copy_only=False)
    if np.any(lengths != POSE_DIM):
        raise DatasetError(f"{directory}: every pose must be a list of {POSE_DIM} floats (found lengths {sorted(set(lengths.tolist()))})")
    poses = np.asarray(column.flatten().to_numpy(zero_copy_only=False), dtype=np.float32).reshape(-1, POSE_DIM)
    if not np.isfinite(poses).all():
        raise DatasetError(f"{directory}: {int((~np.isfinite(poses).all(axis=1)).sum())} pose(s) contain NaN or infinity")
    return poses


def _optional_column(table: pa.Table, name: str, default: object, dtype: DTypeLike) -> np.ndarray:
    if name not in table.column_names:
        return np.full(table.num_rows, default, dtype=dtype)
    values = table.column(name).to_pylist()
    return np.array([default if v is None else v for v in values], dtype=dtype)


def _group_frames(object_ids: list[str], pose_index: np.ndarray, yaw: np.ndarray) -> tuple[list[Frame], np.ndarray]:
    lookup: dict[Frame, int] = {}
    frame_index = np.empty(len(object_ids), dtype=np.int64)
    for row, key in enumerate(zip(object_ids, pose_index.tolist(), yaw.tolist(), strict=True)):
        frame = Frame(str(key[0]), int(key[1]), float(key[2]))
        frame_index[row] = lookup.setdefault(frame, len(lookup))
    return list(lookup), frame_index


def _refuse_test_objects(object_ids: list[str], directory: Path) -> None:
    library = set(library_ids())
    test = sorted({i for i in set(object_ids) if i in library and split_of(i) == "test"})
    if test:
        raise DatasetError(f"{directory}: contains test-split objects {test[:5]}{' ...' if len(test) > 5 else ''}; "
                           "test objects are never used for training")


# ----------------------------------------------------------------------------- splits
def _object_rank(object_id: str, seed: int) -> float:
    digest = hashlib.sha256(f"gd2p-sampler:{seed}:{object_id}".encode()).digest()
    return int.from_bytes(digest[:8], "little") / 2.0**64


def split_objects(object_ids: list[str], val_fraction: float, seed: int = 0) -> tuple[list[str], list[str]]:
    """(train, val) object ids: a seeded, order-independent hold-out of ~val_fraction of the objects.

    With two or more objects and val_fraction > 0 at least one object is held out (and at least
    one kept); a single object cannot be split and is all train.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise DatasetError(f"validation fraction must be in [0, 1), got {val_fraction}")
    ranked = sorted(set(object_ids), key=lambda i: (_object_rank(i, seed), i))
    n_val = 0 if len(ranked) < 2 or val_fraction == 0 else min(len(ranked) - 1, max(1, round(val_fraction * len(ranked))))
    return sorted(ranked[n_val:]), sorted(ranked[:n_val])


def choose_fraction(object_ids: list[str], fraction: float, seed: int = 0) -> list[str]:
    """A seeded subset of ~fraction of the objects (at least one): the data-size experiment's subsets.

    Whole objects are kept or dropped, so a smaller fraction means fewer training shapes, not
    fewer poses per shape.
    """
    if not 0.0 < fraction <= 1.0:
        raise DatasetError(f"--fraction must be in (0, 1], got {fraction}")
    ranked = sorted(set(object_ids), key=lambda i: (_object_rank(i, seed + 7919), i))
    return sorted(ranked[: max(1, math.ceil(fraction * len(ranked) - 1e-9))])


# ----------------------------------------------------------------------------- BPS of the frames
def frame_points(frame: Frame, n_points: int = SURFACE_POINTS, seed: int = SURFACE_SEED) -> np.ndarray:
    """[n_points, 3] surface samples of the frame's object, placed in D as it was validated."""
    obj = load_object(frame.object_id)
    pose_index = None if frame.pose_index == DEFAULT_POSE_INDEX else frame.pose_index
    if pose_index is not None and not 0 <= pose_index < len(obj.resting_poses):
        raise DatasetError(f"{frame.object_id}: resting pose {pose_index} does not exist (it has {len(obj.resting_poses)})")
    points, _ = obj.surface_points(n_points, seed=seed, T_D_O=obj.T_D_O(pose_index, frame.yaw_rad))
    return points


def frame_bps(frames: list[Frame], bps: BasisPointSet, n_points: int = SURFACE_POINTS, seed: int = SURFACE_SEED,
              progress: bool = False) -> np.ndarray:
    """[F, bps.n] float32 BPS of every frame (objects loaded through the object cache)."""
    out = np.empty((len(frames), bps.n), dtype=np.float32)
    for i, frame in enumerate(tqdm(frames, desc="BPS of training frames", unit="frame", disable=not progress)):
        try:
            out[i] = bps.encode(frame_points(frame, n_points, seed))
        except (ObjectLoadError, BPSError) as exc:
            raise DatasetError(f"frame {frame}: {exc}") from exc
    return out

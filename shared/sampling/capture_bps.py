"""What a training frame looks like through the cameras: capture BPS for training the sampler.

Under the evaluation's default perception the planner never sees a mesh: it gets 1-3 depth
captures, reconstructs the object (shared.world.perception) and conditions the sampler on the BPS
of the captured points, in the direction frame of the *reconstruction* (its centre of mass, not the
true one). A model trained only on mesh BPS sees an input it never trained on (the unseen underside
and far side read as far away, the centre is off by millimetres), and with 3 cameras its samples
were the plan's weak part (far more "pose quality" failures than ranked retrieval's; CHANGELOG.md,
"Trained on what the cameras see"). So each training frame is also captured, the planner's own way:

  1. the object, in the frame's resting pose and yaw in D, is put on the table at a random spot of the
     workspace (`CaptureSettings`), with D turned to a random push direction (the cameras stand in
     the world, so the direction decides from where in D they look);
  2. `capture_object` renders it with N simulated depth cameras (noise on), `object_from_cloud`
     reconstructs it from the cloud a request would carry (`cloud_for_request`);
  3. the captured points are encoded in the reconstruction's direction frame (`bps_from_cloud`, as
     the sampler does for a cloud), and the offset of that frame from the true D is kept: a pose
     stored in the true D sits at p + shift in the perceived one (same axes, D origins on the table).

Training (`TrainConfig.capture_fraction`) conditions that share of its rows on one of the frame's
captures, with the pose moved by its shift. A capture that cannot be reconstructed is recorded as
such and those rows keep the mesh BPS.

Store: a directory with `settings.json` (settings, the frames, the dataset's fingerprint) and
`chunk-NNNNN.npz` files of CHUNK_FRAMES frames each, written atomically as they finish: a killed
build resumes with the chunks still missing. Frames are captured in spawned worker processes.
"""
from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import multiprocessing
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from shared.atomic import atomic_write_bytes, atomic_write_text
from shared.frames import direction_frame
from shared.sampling.dataset import DEFAULT_POSE_INDEX, DatasetError, Frame
from shared.world.bps import BasisPointSet

CAPTURE_VERSION = 2  # bump when the same settings give different captures (2: objects of 50-199 points reconstructed)
CHUNK_FRAMES = 16


class CaptureStoreError(DatasetError):
    """A capture store that does not match the frames or settings it is used with."""


@dataclass(frozen=True)
class CaptureSettings:
    """How the training frames are captured (stored with the captures; a resume must match)."""

    cameras: int = 3  # the evaluation's default perception
    per_frame: int = 2  # captures of each frame (each its own spot, direction and camera noise)
    seed: int = 0
    # Where on the table the object stands: around the evaluation's spot (0.40, 0) and a hand's width
    # beyond it each way, so the cameras see it from a spread of angles rather than one.
    x_range_m: tuple[float, float] = (0.33, 0.47)
    y_range_m: tuple[float, float] = (-0.12, 0.12)

    def to_dict(self) -> dict[str, Any]:
        return {**dataclasses.asdict(self), "version": CAPTURE_VERSION}


@dataclass
class FrameCaptures:
    """The capture BPS of frames: [F, V] captures each, V = settings.per_frame."""

    frames: list[Frame]
    bps: np.ndarray  # [F, V, n] float32; a failed capture's row is zeros
    shift_xy: np.ndarray  # [F, V, 2] float32: a pose's offset from the true D to the reconstruction's D
    ok: np.ndarray  # [F, V] bool: the capture was reconstructed
    # Kept only by a store built with `keep_points` (the critic's: its contact features read them):
    # the points each BPS encodes, in the reconstruction's D, zero-padded to BPS_POINTS, and their counts.
    points_d: np.ndarray | None = None  # [F, V, BPS_POINTS, 3] float32
    point_counts: np.ndarray | None = None  # [F, V] int

    def for_frames(self, frames: list[Frame]) -> FrameCaptures:
        """The captures of `frames`, in their order (CaptureStoreError if one was not captured)."""
        row = {frame: i for i, frame in enumerate(self.frames)}
        missing = [f for f in frames if f not in row]
        if missing:
            raise CaptureStoreError(f"{len(missing)} training frames have no captures (e.g. {missing[0]}); "
                                    "rebuild the captures for this dataset")
        rows = np.array([row[f] for f in frames], dtype=np.int64)
        return FrameCaptures(list(frames), self.bps[rows], self.shift_xy[rows], self.ok[rows],
                             None if self.points_d is None else self.points_d[rows],
                             None if self.point_counts is None else self.point_counts[rows])

    def points(self, frame_row: int, variant: int) -> np.ndarray:
        """[M, 3] the points capture `variant` of frame `frame_row` encodes, in the reconstruction's D."""
        if self.points_d is None or self.point_counts is None:
            raise CaptureStoreError("this capture store keeps no points (built without keep_points)")
        return self.points_d[frame_row, variant, :self.point_counts[frame_row, variant]]

    def summary(self) -> dict[str, Any]:
        shift = np.linalg.norm(self.shift_xy[self.ok], axis=-1)
        return {"frames": len(self.frames), "captures": int(self.ok.size), "reconstructed": int(self.ok.sum()),
                "shift_mm_median": float(np.median(shift) * 1e3) if shift.size else None,
                "shift_mm_p90": float(np.percentile(shift, 90) * 1e3) if shift.size else None}


def _frame_seed(frame: Frame, settings: CaptureSettings, variant: int) -> np.random.Generator:
    key = f"{frame.object_id}/{frame.pose_index}/{frame.yaw_rad:.6f}/{settings.seed}/{variant}"
    return np.random.default_rng(int.from_bytes(hashlib.sha256(key.encode()).digest()[:8], "little"))


def capture_points(frame: Frame, variant: int, settings: CaptureSettings,
                   cache_dir: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(the points [M, 3] a capture's BPS encodes, in the reconstruction's D; shift [2]) of one capture of
    `frame`, or None when the capture cannot be reconstructed."""
    # Imported here: PyBullet's renderer and the reconstruction pipeline are needed only by the capture
    # workers, not by every process that reads a finished store.
    from shared.world.objects import ObjectLoadError, load_object
    from shared.world.perception import PerceptionError
    from shared.world.perception.cloud import cloud_for_request
    from shared.world.perception.object_model import bps_points_in_d, object_from_cloud
    from shared.world.sim.camera import capture_object

    rng = _frame_seed(frame, settings, variant)
    obj = load_object(frame.object_id)
    direction_deg = float(rng.uniform(0.0, 360.0))
    xy = (rng.uniform(*settings.x_range_m), rng.uniform(*settings.y_range_m))
    T_world_D = direction_frame(np.array([xy[0], xy[1], 0.0]), direction_deg)
    pose_index = None if frame.pose_index == DEFAULT_POSE_INDEX else frame.pose_index
    T_world_O = T_world_D @ obj.T_D_O(pose_index, frame.yaw_rad)
    capture = capture_object(obj, T_world_O, n_cameras=settings.cameras, seed=int(rng.integers(2**31)))
    try:
        captured = object_from_cloud(cloud_for_request(capture.cloud), cache_dir=cache_dir)
    except (PerceptionError, ObjectLoadError):
        return None
    T_world_Dp = direction_frame(captured.T_world_O[:3, 3], direction_deg)
    points_d = bps_points_in_d(captured.object_points, T_world_Dp)  # what `bps_from_cloud` encodes for a request
    shift = (np.linalg.inv(T_world_Dp) @ T_world_D)[:2, 3]
    return points_d.astype(np.float32), shift.astype(np.float32)


def _capture_chunk(job: tuple[int, list[Frame], CaptureSettings, str, bool]) -> int:
    """Capture every frame of a chunk and write it (in a spawned worker); returns the chunk index."""
    from shared.world.perception.object_model import BPS_POINTS

    index, frames, settings, directory, keep_points = job
    bps = BasisPointSet()
    shape = (len(frames), settings.per_frame)
    out_bps = np.zeros((*shape, bps.n), dtype=np.float32)
    out_shift = np.zeros((*shape, 2), dtype=np.float32)
    ok = np.zeros(shape, dtype=bool)
    points = np.zeros((*shape, BPS_POINTS, 3), dtype=np.float32) if keep_points else None
    counts = np.zeros(shape, dtype=np.int64)
    with tempfile.TemporaryDirectory(prefix="gd2p-captures-") as cache:
        for i, frame in enumerate(frames):
            for v in range(settings.per_frame):
                result = capture_points(frame, v, settings, Path(cache))
                if result is None:
                    continue
                points_d, out_shift[i, v] = result
                out_bps[i, v], ok[i, v] = bps.encode(points_d), True
                if points is not None:
                    points[i, v, :len(points_d)], counts[i, v] = points_d, len(points_d)
    buffer = io.BytesIO()
    kept: dict[str, Any] = {"points_d": points, "point_counts": counts} if points is not None else {}  # Any: savez's
    # keywords include allow_pickle (a bool)
    np.savez(buffer, bps=out_bps, shift_xy=out_shift, ok=ok, **kept)
    atomic_write_bytes(_chunk_path(Path(directory), index), buffer.getvalue())
    return index


def _chunk_path(directory: Path, index: int) -> Path:
    return directory / f"chunk-{index:05d}.npz"


def _frame_dicts(frames: list[Frame]) -> list[dict[str, Any]]:
    return [dataclasses.asdict(f) for f in frames]


def build_captures(frames: list[Frame], directory: str | Path, settings: CaptureSettings, dataset_fingerprint: str,
                   workers: int = 2, progress: bool = True, keep_points: bool = False,
                   desc: str = "captures of training frames") -> FrameCaptures:
    """Capture `frames` into `directory` (resuming a partial build of the same frames and settings);
    `keep_points` also stores the points each BPS encodes (FrameCaptures.points)."""
    directory = Path(directory)
    spec = json.loads(json.dumps({"settings": settings.to_dict(), "dataset_sha256": dataset_fingerprint,
                                  "frames": _frame_dicts(frames), "keep_points": keep_points}))  # as it reads back
    settings_path = directory / "settings.json"
    if settings_path.is_file():
        saved = json.loads(settings_path.read_text())
        if {"keep_points": False, **saved} != spec:  # stores from before keep_points kept none
            raise CaptureStoreError(f"{directory} holds captures of other frames or settings; choose another directory")
    else:
        atomic_write_text(settings_path, json.dumps(spec))
    chunks = [(i, frames[start:start + CHUNK_FRAMES], settings, str(directory), keep_points)
              for i, start in enumerate(range(0, len(frames), CHUNK_FRAMES))]
    todo = [c for c in chunks if not _chunk_path(directory, c[0]).is_file()]
    with tqdm(total=len(frames), initial=len(frames) - sum(len(c[1]) for c in todo), desc=desc,
              unit="frame", disable=not progress, dynamic_ncols=True) as bar:
        if workers <= 1:
            for job in todo:
                _capture_chunk(job)
                bar.update(len(job[1]))
        elif todo:
            sizes = {c[0]: len(c[1]) for c in todo}
            with multiprocessing.get_context("spawn").Pool(workers) as pool:
                for done in pool.imap_unordered(_capture_chunk, todo):
                    bar.update(sizes[done])
    return load_captures(directory)


def load_captures(directory: str | Path) -> FrameCaptures:
    """A finished capture store (CaptureStoreError if it is missing chunks)."""
    directory = Path(directory)
    settings_path = directory / "settings.json"
    if not settings_path.is_file():
        raise CaptureStoreError(f"{directory}: no capture store here (settings.json missing)")
    spec = json.loads(settings_path.read_text())
    frames = [Frame(**f) for f in spec["frames"]]
    n_chunks = -(-len(frames) // CHUNK_FRAMES)
    missing = [i for i in range(n_chunks) if not _chunk_path(directory, i).is_file()]
    if missing:
        raise CaptureStoreError(f"{directory}: {len(missing)} of {n_chunks} chunks not captured yet; "
                                "run the build again to finish it")
    parts = [np.load(_chunk_path(directory, i)) for i in range(n_chunks)]
    kept = (np.concatenate([p["points_d"] for p in parts]), np.concatenate([p["point_counts"] for p in parts])) \
        if spec.get("keep_points") else (None, None)
    return FrameCaptures(frames, np.concatenate([p["bps"] for p in parts]), np.concatenate([p["shift_xy"] for p in parts]),
                         np.concatenate([p["ok"] for p in parts]), *kept)


def capture_store_spec(directory: str | Path) -> dict[str, Any]:
    """settings.json of a capture store: what a checkpoint's manifest records about its captures."""
    spec = json.loads((Path(directory) / "settings.json").read_text())
    return {"settings": spec["settings"], "dataset_sha256": spec["dataset_sha256"], "frames": len(spec["frames"])}

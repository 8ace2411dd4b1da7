"""Sampling push poses from a trained checkpoint: `PoseSampler(checkpoint).sample(object, frame, k)`.

An object is a library id, a mesh file path, an `ObjectModel`, or a point cloud ([N, 3] metres).
The frame is a `DirectionFrame` (the object's pose in the world and the push direction), which
fixes the direction frame D (shared.frames.direction_frame: origin under the object's centre of
mass, +x along the push). The object's surface points are expressed in D, encoded with the
checkpoint's BPS basis, and the model samples K poses in D; they are also returned in the world.

- A mesh / library object with no frame rests in its default pose at the world origin with
  yaw 0 and is pushed along world +x (then D = world).
- A point cloud is in the world frame, with the frame's object position its centre of mass; with
  no frame it is taken to be already in D.

Concurrent `sample` calls (e.g. a service's job threads) are batched: the BPS is computed in the
caller's thread, then one batching thread runs every request queued at that moment through the
network together (same sampler and step count), so the batch costs about one request's network
time. Each request draws its noise from its own seeded generator, so its poses do not depend on
what it was batched with.

Outputs are cleaned for the robot: the r6 block is Gram–Schmidt-orthonormalised (an exact
rotation) and joints are clamped to the hand's limits stored in the checkpoint.
"""
from __future__ import annotations

import queue
import threading
import time
from collections import OrderedDict
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from shared.contracts.messages import DirectionFrame, ObjectPose
from shared.frames import (
    JOINTS,
    ROTATION_6D,
    frame_object_transform,
    frame_transform,
    invert_transform,
    matrix_to_pos_quat,
    matrix_to_r6,
    points_world_to_d,
    poses_d_to_world,
    r6_to_matrix,
    transform_points,
)
from shared.robots.hands import load_hand
from shared.sampling.checkpoint import SamplerCheckpoint, checkpoint_id, load_checkpoint
from shared.sampling.critic import SuccessCritic
from shared.sampling.diffusion import (
    DiffusionConfigError,
    GradientGuidance,
    Guide,
    check_guidance_scale,
    check_noise_scale,
    default_noise_scale,
    resolve_steps,
    sample_normalized,
)
from shared.sampling.guidance import CriticGuide
from shared.world.bps import BPSError
from shared.world.objects import ObjectLoadError, ObjectModel, load_object

ObjectInput = str | Path | ObjectModel | np.ndarray
MAX_POSES_PER_REQUEST = 1000
MAX_BATCH_POSES = 8192  # rows per network batch; larger queues run as several batches
_OBJECT_CACHE_SIZE = 64


class SamplerInputError(ValueError):
    """A request the sampler cannot serve: unknown / broken object, empty cloud, outside the BPS ball, bad k."""


@dataclass
class SampleResult:
    """K poses in D and in the world, and how they were obtained."""

    poses_d: np.ndarray  # [K, 25] float64
    poses_world: np.ndarray  # [K, 25] float64
    T_world_D: np.ndarray  # [4, 4]
    latency_s: float  # object points + BPS + denoising (+ queueing behind other requests)
    sampler: str
    steps: int
    object_label: str
    bps: np.ndarray | None = None  # [n_basis] the object's BPS in D, when the sampler encoded one
    noise_scale: float = 1.0  # the sampling temperature the poses were drawn with
    points_d: np.ndarray | None = None  # [N, 3] the surface points in D the BPS encodes


@dataclass
class _Job:
    bps: torch.Tensor  # [n_basis]
    k: int
    seed: int
    sampler: str
    steps: int
    noise_scale: float
    future: Future[np.ndarray]
    guide: Guide | None = None
    guidance: GradientGuidance | None = None


# ----------------------------------------------------------------------------- object placement
def default_frame(obj: ObjectModel, direction_deg: float = 0.0) -> DirectionFrame:
    """`obj` resting in its default pose at the world origin with yaw 0, pushed along `direction_deg`."""
    position, quaternion = matrix_to_pos_quat(obj.T_D_O())
    return DirectionFrame(object_pose=ObjectPose(position=tuple(position), quaternion_xyzw=tuple(quaternion)),
                          yaw_deg=float(direction_deg))


class ObjectPoints:
    """An object's surface samples placed in D; samples (in O) of recent objects are cached, so repeated
    requests skip mesh loading. Every BPS query of the sampler (diffusion and nearest neighbour) goes
    through `in_d`, so both see exactly the same points."""

    def __init__(self, n_points: int, seed: int):
        self.n_points, self.seed = n_points, seed
        self._cache: OrderedDict[str, tuple[ObjectModel, np.ndarray]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, obj: str | Path | ObjectModel) -> tuple[ObjectModel, np.ndarray]:
        key = obj.key if isinstance(obj, ObjectModel) else _source_key(obj)
        with self._lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        model = obj if isinstance(obj, ObjectModel) else _load(obj)
        points, _ = model.surface_points(self.n_points, seed=self.seed)
        with self._lock:
            self._cache[key] = (model, points)
            while len(self._cache) > _OBJECT_CACHE_SIZE:
                self._cache.popitem(last=False)
        return model, points

    def in_d(self, obj: ObjectInput, frame: DirectionFrame | None = None) -> tuple[np.ndarray, np.ndarray, str]:
        """(object surface points in D [N, 3], T_world_D, a label naming the object); see the module docstring."""
        if isinstance(obj, np.ndarray):
            cloud = np.asarray(obj, dtype=np.float64)
            if cloud.ndim != 2 or cloud.shape[-1] != 3:
                raise SamplerInputError(f"a point cloud must be [N, 3], got shape {cloud.shape}")
            if frame is None:
                return cloud, np.eye(4), "point cloud (in D)"
            T_world_D = frame_transform(frame)
            return points_world_to_d(cloud, T_world_D), T_world_D, "point cloud"
        model, points_o = self.get(obj)
        frame = frame or default_frame(model)
        T_world_D = frame_transform(frame)
        T_D_O = invert_transform(T_world_D) @ frame_object_transform(frame)
        return transform_points(T_D_O, points_o), T_world_D, model.id


def _source_key(id_or_path: str | Path) -> str:
    """Cache key of an id or mesh file; a file's key changes when the file does."""
    path = Path(id_or_path)
    if path.is_file():
        stat = path.stat()
        return f"{path.resolve()}:{stat.st_size}:{stat.st_mtime_ns}"
    return str(id_or_path)


def _load(id_or_path: str | Path) -> ObjectModel:
    try:
        return load_object(id_or_path)
    except ObjectLoadError as exc:
        raise SamplerInputError(str(exc)) from exc


# ----------------------------------------------------------------------------- the sampler
class PoseSampler:
    """A loaded checkpoint serving `sample` calls, batching concurrent ones. Thread-safe."""

    def __init__(self, checkpoint: str | Path | SamplerCheckpoint, device: str | torch.device = "cpu",
                 max_batch_poses: int = MAX_BATCH_POSES):
        if isinstance(checkpoint, SamplerCheckpoint):
            self.checkpoint, self.checkpoint_id = checkpoint, "in-memory"
        else:
            self.checkpoint, self.checkpoint_id = load_checkpoint(checkpoint), checkpoint_id(checkpoint)
        self.hand = self.checkpoint.hand
        self.device = torch.device(device)
        self.model = self.checkpoint.build_model().to(self.device)
        self.guidance_scale = self.checkpoint.guidance_scale
        check_guidance_scale(self.guidance_scale, self.checkpoint.model_config)
        self.normalizer = self.checkpoint.normalizer
        self.bps = self.checkpoint.bps
        self.max_batch_poses = max_batch_poses
        self._objects = ObjectPoints(self.checkpoint.surface_points, self.checkpoint.surface_seed)
        self._queue: queue.Queue[_Job | None] = queue.Queue()
        self._thread: threading.Thread | None = None
        self._start_lock = threading.Lock()
        self._closed = False

    def __enter__(self) -> PoseSampler:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the batching thread (pending requests are finished first)."""
        with self._start_lock:
            self._closed = True
            thread, self._thread = self._thread, None
        if thread is not None:
            self._queue.put(None)
            thread.join()

    # ------------------------------------------------------------------ public API
    def points_in_d(self, obj: ObjectInput, frame: DirectionFrame | None = None) -> tuple[np.ndarray, np.ndarray, str]:
        """(object surface points in D [N, 3], T_world_D, a label naming the object)."""
        return self._objects.in_d(obj, frame)

    def encode(self, obj: ObjectInput, frame: DirectionFrame | None = None) -> tuple[np.ndarray, np.ndarray, str]:
        """(BPS [n_basis] float32 of the object in D, T_world_D, label); SamplerInputError if it cannot be encoded."""
        points_d, T_world_D, label = self.points_in_d(obj, frame)
        return self.encode_points(points_d, label), T_world_D, label

    def encode_points(self, points_d: np.ndarray, label: str) -> np.ndarray:
        """BPS [n_basis] float32 of surface points [N, 3] in D; SamplerInputError (naming `label`) if impossible."""
        try:
            return self.bps.encode(points_d)
        except BPSError as exc:
            raise SamplerInputError(f"{label}: {exc}") from exc

    def sample(self, obj: ObjectInput, frame: DirectionFrame | None = None, k: int = 200, sampler: str = "ddpm",
               steps: int | None = None, seed: int = 0, noise_scale: float | None = None,
               critic: SuccessCritic | None = None, guidance: GradientGuidance | None = None) -> SampleResult:
        """K push poses for `obj` placed by `frame` (see the module docstring for defaults); `noise_scale`
        is the sampling temperature (`sample_normalized`; None: `default_noise_scale()`); `critic` with
        `guidance` steers the last denoising steps up the critic's log P(success) (`guidance.CriticGuide`)."""
        started = time.perf_counter()
        noise_scale = _resolve_noise_scale(noise_scale)
        step_count = _check_request(k, sampler, steps, seed, noise_scale)
        if (critic is None) != (guidance is None):
            raise SamplerInputError("critic guidance needs both a critic and its GradientGuidance settings")
        points_d, T_world_D, label = self.points_in_d(obj, frame)
        bps = self.encode_points(points_d, label)
        guide = None if critic is None else CriticGuide(critic, load_hand(self.hand), bps, points_d, self.normalizer)
        poses_d = self.sample_from_bps(bps, k, sampler, steps, seed, noise_scale, guide, guidance)
        return SampleResult(poses_d, poses_d_to_world(poses_d, T_world_D), T_world_D, time.perf_counter() - started,
                            sampler, step_count, label, bps, noise_scale, points_d)

    def sample_from_bps(self, bps: np.ndarray, k: int, sampler: str = "ddpm", steps: int | None = None, seed: int = 0,
                        noise_scale: float | None = None, guide: Guide | None = None,
                        guidance: GradientGuidance | None = None) -> np.ndarray:
        """[k, 25] poses in D for an already encoded object (steered by `guide` under `guidance`, when given);
        joins the current batch."""
        noise_scale = _resolve_noise_scale(noise_scale)
        step_count = _check_request(k, sampler, steps, seed, noise_scale)
        bps_tensor = torch.as_tensor(np.asarray(bps, dtype=np.float32)).reshape(-1)
        if bps_tensor.numel() != self.bps.n:
            raise SamplerInputError(f"BPS must have {self.bps.n} values (this checkpoint's basis), got {bps_tensor.numel()}")
        if (guide is None) != (guidance is None):
            raise SamplerInputError("a guide needs its GradientGuidance settings, and settings need a guide")
        job = _Job(bps_tensor, int(k), int(seed), sampler, step_count, float(noise_scale), Future(), guide, guidance)
        self._ensure_thread()
        self._queue.put(job)
        return job.future.result()

    # ------------------------------------------------------------------ batching
    def _ensure_thread(self) -> None:
        with self._start_lock:
            if self._closed:
                raise RuntimeError("this PoseSampler is closed")
            if self._thread is None:
                self._thread = threading.Thread(target=self._serve, name=f"sampler-{self.hand}", daemon=True)
                self._thread.start()

    def _serve(self) -> None:
        while True:
            first = self._queue.get()
            if first is None:
                return
            jobs, stop = [first], False
            while True:  # everything queued right now joins this batch
                try:
                    job = self._queue.get_nowait()
                except queue.Empty:
                    break
                if job is None:
                    stop = True
                    break
                jobs.append(job)
            for batch in self._batches(jobs):
                self._run(batch)
            if stop:
                return

    def _batches(self, jobs: list[_Job]) -> list[list[_Job]]:
        """Jobs grouped by (sampler, steps, noise scale, gradient guidance), each group cut to at most max_batch_poses rows."""
        groups: dict[tuple[str, int, float, GradientGuidance | None], list[list[_Job]]] = {}
        for job in jobs:
            chunks = groups.setdefault((job.sampler, job.steps, job.noise_scale, job.guidance), [[]])
            if chunks[-1] and sum(j.k for j in chunks[-1]) + job.k > self.max_batch_poses:
                chunks.append([])
            chunks[-1].append(job)
        return [chunk for chunks in groups.values() for chunk in chunks]

    def _run(self, jobs: list[_Job]) -> None:
        try:
            bps = torch.stack([job.bps for job in jobs]).to(self.device)
            generators = [torch.Generator(device=self.device).manual_seed(job.seed) for job in jobs]
            guidance = jobs[0].guidance
            outputs = sample_normalized(self.model, bps, [job.k for job in jobs], generators, jobs[0].sampler, jobs[0].steps,
                                        jobs[0].noise_scale, self.guidance_scale,
                                        [job.guide for job in jobs] if guidance is not None else None, guidance)
            for job, output in zip(jobs, outputs, strict=True):
                job.future.set_result(self.clean_poses(output))
        except Exception as exc:  # deliver the failure to every waiting caller, keep serving
            for job in jobs:
                if not job.future.done():
                    job.future.set_exception(exc)

    def clean_poses(self, normalized: torch.Tensor) -> np.ndarray:
        """Normalised poses [n, 25] -> poses in D for the robot: an orthonormal rotation block, joints within limits."""
        poses = self.normalizer.unnormalize(normalized.float().cpu()).double()
        rotation = r6_to_matrix(poses[:, ROTATION_6D])
        poses[:, ROTATION_6D] = matrix_to_r6(rotation)
        lower, upper = self.checkpoint.joint_lower.double(), self.checkpoint.joint_upper.double()
        poses[:, JOINTS] = torch.minimum(torch.maximum(poses[:, JOINTS], lower), upper)
        return poses.numpy()


def check_count_and_seed(k: int, seed: int) -> None:
    """SamplerInputError unless 1 <= k <= MAX_POSES_PER_REQUEST and seed >= 0."""
    if not 1 <= int(k) <= MAX_POSES_PER_REQUEST:
        raise SamplerInputError(f"k must be in 1..{MAX_POSES_PER_REQUEST}, got {k}")
    if int(seed) < 0:
        raise SamplerInputError(f"seed must be >= 0, got {seed}")


def _resolve_noise_scale(noise_scale: float | None) -> float:
    try:
        return default_noise_scale() if noise_scale is None else float(noise_scale)
    except DiffusionConfigError as exc:
        raise SamplerInputError(str(exc)) from exc


def _check_request(k: int, sampler: str, steps: int | None, seed: int, noise_scale: float = 1.0) -> int:
    """Validate a request's settings; returns the number of denoising steps it will run."""
    check_count_and_seed(k, seed)
    try:
        check_noise_scale(noise_scale)
        return resolve_steps(sampler, steps)
    except DiffusionConfigError as exc:
        raise SamplerInputError(str(exc)) from exc

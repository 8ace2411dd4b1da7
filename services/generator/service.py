"""Bus adapter of the generator service: a GenerationJob in, a GenerationResult out.

Placement on the bus: the object rests in the job's resting pose (`pose_index`, default: the
object's default pose) turned by `yaw_rad` about D's z (default 0) - a ValidationJob with the same
`pose_index` and a frame turned by that yaw places it the same way, so poses validate as generated.
Each job is deterministic for its seed (torch.Generator everywhere; one torch thread per worker
process, docs/architecture.md §Compute), so a re-dispatched job gives the same poses on any worker. The optimisation
checks the job's deadline after every iteration (`shared.bus.worker.check_deadline`): a job past it
ends with ErrorReply "timeout" and frees its worker.
"""
from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

import numpy as np

from shared.bus.worker import check_deadline
from shared.contracts.errors import ServiceError
from shared.contracts.messages import GenerationJob, GenerationResult, Message, ObjectRef
from shared.robots.hands import load_hand
from shared.synthesis.config import GenerationConfig, GenerationConfigError
from shared.synthesis.init import InitialisationError
from shared.synthesis.scene import PushScene
from shared.synthesis.synthesis import GenerationError, GenerationOutput, generate
from shared.world.object_refs import load_object_ref
from shared.world.objects import ObjectLoadError, ObjectModel

SERVICE = "generator"
# A job's deadline (Worker job_budget): its iterations times the measured cost of one at its batch size, with a
# margin, capped by the worker's deadline. Measured on a loaded 2-core machine, one torch thread: 9.5 ms an
# iteration at batch 8, 30.5 ms at 64, 97.5 ms at 256 (about 6 ms + 0.36 ms per pose).
SECONDS_PER_ITERATION = 0.01
SECONDS_PER_POSE_ITERATION = 0.0004
BUDGET_MARGIN = 4.0
BUDGET_BASE_S = 30.0  # loading the object's SDF grid and the hand on a worker that has not seen them
# Objects (their SDF grid is the costly part to load) are kept per id; scenes per placement, since a
# data-engine build turns every job's object by its own random yaw (a scene is cheap from its object).
_OBJECTS: dict[str, ObjectModel] = {}
_MAX_CACHED_OBJECTS = 16
_SCENES: dict[tuple[str, int | None, float], PushScene] = {}
_MAX_CACHED_SCENES = 16


def _limit_torch_threads() -> None:
    """Busy worker processes share the cores: one torch thread each (docs/architecture.md §Compute)."""
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)


def job_budget(job: Message) -> float:
    """Seconds a GenerationJob may take: its iterations (the default's when it names none) at its batch size."""
    if not isinstance(job, GenerationJob):
        return BUDGET_BASE_S
    iterations = job.iterations or GenerationConfig().iterations
    return BUDGET_BASE_S + BUDGET_MARGIN * iterations * (SECONDS_PER_ITERATION + job.batch_size * SECONDS_PER_POSE_ITERATION)


def resolve_object(ref: ObjectRef) -> ObjectModel:
    """The library object or user mesh of a job; a bad one is a bad_request naming the problem."""
    try:
        return load_object_ref(ref)
    except ObjectLoadError as exc:
        raise ServiceError("bad_request", f"the generator needs an object mesh or library id: {exc}") from exc


def cached_object(ref: ObjectRef) -> ObjectModel:
    """The job's object, kept for later jobs on it (oldest dropped first)."""
    key = ref.object_id
    if key not in _OBJECTS:
        obj = resolve_object(ref)
        if len(_OBJECTS) >= _MAX_CACHED_OBJECTS:
            _OBJECTS.pop(next(iter(_OBJECTS)))
        _OBJECTS[key] = obj
    return _OBJECTS[key]


def scene_for(ref: ObjectRef, config: GenerationConfig, pose_index: int | None = None,
              yaw_rad: float = 0.0) -> PushScene:
    """The object resting in `pose_index` (None: its default pose) turned by `yaw_rad` in D, cached per placement."""
    key = (ref.object_id, pose_index, yaw_rad)
    if key not in _SCENES:
        obj = cached_object(ref)
        try:
            scene = PushScene.from_object(obj, pose_index, yaw_rad, surface_points=config.object_points,
                                          check_points=config.penetration_check_points)
        except ValueError as exc:  # a resting pose the object does not have
            raise ServiceError("bad_request", f"generator: {exc}") from exc
        if len(_SCENES) >= _MAX_CACHED_SCENES:
            _SCENES.pop(next(iter(_SCENES)))
        _SCENES[key] = scene
    return _SCENES[key]


def job_config(job: GenerationJob, base: GenerationConfig | None = None) -> GenerationConfig:
    """The default configuration with the job's iteration count, contacts per pose and mode."""
    base = base or GenerationConfig()
    try:
        return base.replace(iterations=job.iterations, contacts_per_pose=job.contacts_per_pose,
                            grasp_only=job.grasp_only)
    except GenerationConfigError as exc:
        raise ServiceError("bad_request", f"generator: {exc}") from exc


def run_job(job: GenerationJob) -> GenerationResult:
    """Optimise `job.batch_size` pre-contact push poses for `job.object` at the job's placement (paper Eq. 1)."""
    _limit_torch_threads()
    config = job_config(job)
    scene = scene_for(job.object, config, job.pose_index, job.yaw_rad)
    try:
        output = generate(scene, load_hand(job.hand), job.batch_size, job.seed, config,
                          progress=lambda iterations: check_deadline())
    except (GenerationError, InitialisationError, ValueError) as exc:
        raise ServiceError("bad_request", f"generator: {exc}") from exc
    return to_result(job, output)


def to_result(job: GenerationJob, output: GenerationOutput) -> GenerationResult:
    return GenerationResult(
        job_id=job.id,
        hand=job.hand,
        object_id=output.object_id,
        poses=output.poses.astype(np.float32),
        energies={name: values.astype(np.float32) for name, values in output.energies.items()},
        palm_normals=output.palm_normals.astype(np.float32),
        max_penetration_m=output.max_penetration_m.astype(np.float32),
        elapsed_s=output.elapsed_s,
        energy_history={name: values.astype(np.float32) for name, values in output.history.items()},
    )


def handlers() -> dict[type[Message], Callable[[Any], Message]]:  # each handler takes its key's type
    """Message type -> handler, served by every generator worker."""
    return {GenerationJob: run_job}

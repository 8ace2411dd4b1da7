"""Bus adapter of the validator service: a ValidationJob in, a ValidationResult out.

Each worker process runs one PyBullet client per job thread (the simulators are thread-local, so a
worker started with concurrency > 1 stays correct; one process per core is what scales,
docs/architecture.md §Compute). Jobs on the same object and hand reuse the scene. The push physics is deterministic, and the
job seed fixes the augmentation copies, so a job gives the same result on any worker.

Placement of a floating-hand job: the object rests in `job.pose_index` (its default resting pose
when None) turned about D's z as `job.frame` says (yaw 0 without a frame) - the placement a
GenerationJob with the same `pose_index` and `yaw_rad` optimised against (`placement`).

Arm rollouts (`with_arm=True`: a planned push played with the arm, for the planner's
ranking) go to `rollout.rollout`.

Deadline: a worker gives each job a budget proportional to its size (`job_budget`: its pushes or
rollouts times their measured cost, with a margin), never more than JOB_DEADLINE_S and less when its
caller waits less; the floating-hand episode loop checks it between episodes
(`shared.bus.worker.check_deadline`), so a job too big for its budget ends with ErrorReply "timeout"
and frees its worker within one episode. Small jobs (`is_express`: the planner's prescreen pushes and
rollouts) get a thread of their own when the worker is busy with a big one, so a push is not held up
behind a data-engine job.
"""
from __future__ import annotations

import dataclasses
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import DTypeLike

from shared.bus.worker import check_deadline
from shared.contracts.errors import ServiceError
from shared.contracts.messages import (
    AugmentedOutcomes,
    Message,
    ObjectRef,
    PhysicsSettings,
    ValidationJob,
    ValidationResult,
)
from shared.frames import object_yaw_in_d, resting_tilt_deg
from shared.robots.hands import load_hand
from shared.validation.augment import COPIES_PER_SUCCESS
from shared.validation.push import PushInputError, PushOutcome, table_object
from shared.validation.rollout import rollout
from shared.validation.validator import ValidationRun, Validator
from shared.world.object_refs import load_object_ref
from shared.world.objects import ObjectLoadError, ObjectModel
from shared.world.sim import PhysicsParams, SimError

SERVICE = "validator"
DEFAULT_PARAMS = PhysicsParams()
# The longest any one job may hold a worker, whatever its size: a default data-engine job (32 candidates
# + 10 augmented copies of each success) runs in under a minute and gets about 6 min by `job_budget`.
JOB_DEADLINE_S = 600.0
# Measured costs (bench/validator.py: 4.4 validated pushes/s on one process; bench/push.py: up to 6
# rollouts of a push in about 0.5 s on 2 validators). The margin covers a loaded machine (2-3x slower
# while the test suite runs) and a cold worker's scene set-up.
SECONDS_PER_PUSH = 0.25
SECONDS_PER_ROLLOUT = 0.5
BUDGET_MARGIN = 4.0
BUDGET_BASE_S = 20.0  # loading the object and hand, building the scene on a worker that has not seen them
EXPRESS_MAX_S = 60.0  # jobs whose budget is at most this may take the express thread
# With an explicit resting pose, the frame's object may lean this far from it (numerical noise of a
# quaternion round trip is ~1e-7 deg); a frame of another resting pose is refused, not silently turned.
MAX_RESTING_TILT_DEG = 1.0

_local = threading.local()


def _limit_torch_threads() -> None:
    """Busy worker processes share the cores: one torch thread each (docs/architecture.md §Compute)."""
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)


def _validator() -> Validator:
    validator = getattr(_local, "validator", None)
    if validator is None:
        validator = _local.validator = Validator(DEFAULT_PARAMS)
    return validator


def job_budget(job: Message) -> float:
    """Seconds a job may take: its pushes (every augmented copy counted as if each pose succeeded) or its
    rollouts (each physics draw one more) times their measured cost, with a margin, capped at JOB_DEADLINE_S."""
    if not isinstance(job, ValidationJob):
        return JOB_DEADLINE_S
    poses = len(job.poses.to_numpy())
    if job.with_arm:
        work = poses * (1 + job.physics_draws) * SECONDS_PER_ROLLOUT
    else:
        work = poses * (1 + (COPIES_PER_SUCCESS if job.augment else 0)) * SECONDS_PER_PUSH
    return min(JOB_DEADLINE_S, BUDGET_BASE_S + BUDGET_MARGIN * work)


def is_express(job: Message) -> bool:
    """A small job (a few pushes or rollouts): it may run beside a big one instead of waiting for it."""
    return isinstance(job, ValidationJob) and job_budget(job) <= EXPRESS_MAX_S


def params_for(settings: PhysicsSettings | None) -> PhysicsParams:
    """The service defaults, overridden by a job's solver settings and push speed."""
    if settings is None:
        return DEFAULT_PARAMS
    return dataclasses.replace(DEFAULT_PARAMS, solver_iterations=settings.solver_iterations,
                               time_step_s=settings.time_step_s, push_speed_mps=settings.push_speed_mps)


def resolve_object(ref: ObjectRef) -> ObjectModel:
    """The library object or user mesh of a job; a bad one is a bad_request naming the problem."""
    try:
        return load_object_ref(ref)
    except ObjectLoadError as exc:
        raise ServiceError("bad_request", f"the validator needs an object mesh or library id: {exc}") from exc


def validate(job: ValidationJob) -> ValidationResult:
    """Push `job.object` with the hand at each pose of `job.poses` and judge the outcome."""
    if job.with_arm:
        return rollout(job, params_for(job.settings))
    started = time.perf_counter()
    obj = resolve_object(job.object)
    hand = load_hand(job.hand)
    pose_index, yaw = placement(job, obj)
    check_deadline()
    try:
        run = _validator().validate(
            table_object(obj, pose_index, yaw), hand, job.poses.to_numpy().astype(np.float64), params=params_for(job.settings),
            push_distance_m=job.push_distance_m, augment=job.augment, seed=job.seed,
            progress=lambda episodes: check_deadline())
    except (PushInputError, SimError) as exc:
        raise ServiceError("bad_request", f"validator: {exc}") from exc
    return to_result(job, obj.id, run, time.perf_counter() - started)


def placement(job: ValidationJob, obj: ObjectModel) -> tuple[int | None, float]:
    """(resting pose index, yaw in D) of a floating-hand job's object; bad_request for a pose it cannot be in."""
    if job.pose_index is not None and job.pose_index >= len(obj.resting_poses):
        raise ServiceError("bad_request", f"validator: {obj.id} has {len(obj.resting_poses)} resting poses; "
                                          f"pose_index {job.pose_index} does not exist")
    rest = obj.default_pose if job.pose_index is None else obj.resting_poses[job.pose_index]
    if job.frame is None:
        return job.pose_index, 0.0
    if job.pose_index is not None:
        tilt = resting_tilt_deg(job.frame, rest.rotation)
        if tilt > MAX_RESTING_TILT_DEG:
            raise ServiceError("bad_request", f"validator: the frame's object is {tilt:.1f} deg away from resting pose "
                                              f"{job.pose_index} of {obj.id} turned about the vertical")
    return job.pose_index, object_yaw_in_d(job.frame, rest.rotation)


def outcome_arrays(outcomes: list[PushOutcome]) -> dict[str, np.ndarray]:
    """PushOutcome list -> the column arrays of PushOutcomes."""
    def column(name: str, dtype: DTypeLike) -> np.ndarray:
        return np.array([getattr(o, name) for o in outcomes], dtype=dtype)

    return {
        "success": column("success", bool),
        "position_error_m": column("position_error_m", np.float64),
        "rotation_deg": column("rotation_deg", np.float64),
        "max_tilt_deg": column("max_tilt_deg", np.float64),
        "contact_kept": column("contact_kept", bool),
        "hand_table_contact": column("hand_table_contact", bool),
        "initial_penetration_m": column("initial_penetration_m", np.float64),
    }


def to_result(job: ValidationJob, object_id: str, run: ValidationRun, elapsed_s: float) -> ValidationResult:
    augmented = None
    if run.augmented is not None:
        augmented = AugmentedOutcomes(poses=run.augmented.poses, parent_index=run.augmented.parent_index,
                                      **outcome_arrays(run.augmented.outcomes))
    return ValidationResult(job_id=job.id, hand=job.hand, object_id=object_id, augmented=augmented,
                            elapsed_s=elapsed_s, **outcome_arrays(run.outcomes))


def handlers() -> dict[type[Message], Callable[[Any], Message]]:  # each handler takes its key's type
    """Message type -> handler, served by every validator worker (called once at worker start-up)."""
    _limit_torch_threads()
    return {ValidationJob: validate}

"""What the planner decided for each push, for the live view and the recording: a `PushDecision`
(the decision's reproducibility metadata for `--resim` is shared/planning/decision.py).

`DecisionTap` wraps a pipeline's services (`PushServices`) and watches them work: the sampler's reply (the
candidates and the critic's scores), the arm rollouts sent to the validators (each plan with its predicted
object path) and the plan sent to the robot. Just before a plan is executed it hands a `PushDecision` to
`on_decision` (the planner service publishes it on the bus; an in-process evaluation feeds a view directly).
It needs nothing from the pipeline's internals: only what crosses its service boundary.
"""
from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np

from shared.contracts.messages import (
    ObjectPath,
    Plan,
    PushDecision,
    RolloutPreview,
    SampleRequest,
    SampleResponse,
    SimWorld,
    ValidationJob,
    ValidationResult,
)
from shared.frames import frame_transform, poses_d_to_world
from shared.planning.cancellation import Cancellation
from shared.planning.monitor import PushMonitor
from shared.planning.outcome import Execution
from shared.planning.pipeline import PushServices

log = logging.getLogger("gd2p.decision")

OnDecision = Callable[[PushDecision], None]


@dataclass
class _Rollout:
    job: ValidationJob
    result: Future[ValidationResult]


class DecisionTap:
    """Wraps `PushServices`; calls `on_decision(PushDecision)` before each execution (see the module docstring).

    `begin(request_id)` starts a request (its pushes are numbered from 0); `decisions` are those of the
    current request, for its recording. A failing `on_decision` is logged, never raised into the push."""

    def __init__(self, services: PushServices, on_decision: OnDecision | None = None, keep: int | None = None):
        self.inner = services
        self.keep = keep  # decisions kept for the recording (None: all of the request's; an evaluation keeps 1)
        self.on_decision = on_decision
        self.decisions: list[PushDecision] = []
        self._lock = threading.Lock()
        self._request_id: str | None = None
        self._sample: tuple[SampleRequest, SampleResponse] | None = None
        self._rollouts: list[_Rollout] = []
        self._pushes = 0  # decisions made for the current request
        self._stopped = False  # the last execution was a push the closed-loop monitor stopped: a back-out follows

    def services(self) -> PushServices:
        return PushServices(sample=self.sample, validate=self.validate, execute=self.execute)

    def begin(self, request_id: str | None) -> None:
        with self._lock:
            self._request_id = request_id
            self.decisions = []
            self._pushes = 0
            self._sample = None
            self._rollouts = []
            self._stopped = False

    def sample(self, request: SampleRequest) -> SampleResponse:
        reply = self.inner.sample(request)
        with self._lock:
            self._sample = (request, reply)
        return reply

    def validate(self, job: ValidationJob) -> Future[ValidationResult]:
        future = self.inner.validate(job)
        if job.with_arm:
            with self._lock:
                self._rollouts.append(_Rollout(job, future))
        return future

    def execute(self, plan: Plan, world: SimWorld | None, cancel: Cancellation,
                monitor: PushMonitor | None = None) -> Execution:
        backing_out = self._stopped and monitor is None
        if self.on_decision is not None and not backing_out:
            try:
                decision = self.decision(plan)
            except Exception:  # never let the view break a push
                log.exception("could not build the push decision")
                decision = None
            if decision is not None:
                try:
                    self.on_decision(decision)
                except Exception:
                    log.exception("could not hand on the push decision")
        execution = self.inner.execute(plan, world, cancel, monitor)
        self._stopped = monitor is not None and execution.final.status == "stopped"
        return execution

    def decision(self, plan: Plan) -> PushDecision | None:
        """The decision behind executing `plan`, from what the services saw since the last execution (None when
        nothing says where the object is: neither a sample nor a rollout, e.g. a fixed pose chosen at random).

        Candidates: the sampler's poses (in D, placed by this push's frame); without a sample (the fixed
        spatula pose), the poses the rollouts pushed from, without scores."""
        with self._lock:
            sampled, rollouts = self._sample, self._rollouts
            self._rollouts = []
            job = rollouts[-1].job if rollouts else None
            if sampled is None and job is None:
                return None
            frame = job.frame if job is not None and job.frame is not None else None
            if sampled is not None:
                request, reply = sampled
                frame = frame or request.frame
                poses_d = reply.poses_d.to_numpy().astype(np.float64)
                scores = reply.success_probability
                obj, hand = request.object, request.hand
            else:
                assert job is not None
                poses_d = np.unique(np.concatenate([r.job.poses.to_numpy() for r in rollouts]).astype(np.float64), axis=0)
                scores = None
                obj, hand = job.object, job.hand
            if frame is None:
                return None
            candidates = poses_d_to_world(poses_d, frame_transform(frame))
            previews = [_preview(r) for r in rollouts]
            chosen = next((i for i, r in enumerate(previews) if _is_prefix(r.plan, plan)), None)
            decision = PushDecision(
                request_id=self._request_id, push_index=self._pushes, hand=hand, arm=plan.arm,
                object=obj, frame=frame, distance_m=job.push_distance_m if job else None,
                obstacles=list(job.obstacles) if job else [], candidates_world=candidates,
                critic_scores=scores, rollouts=previews, chosen=chosen, plan=plan)
            self.decisions.append(decision)
            self._pushes += 1
            if self.keep is not None:
                del self.decisions[:-self.keep]
            return decision


def _preview(rollout: _Rollout) -> RolloutPreview:
    plan = rollout.job.plan
    assert plan is not None  # an arm rollout carries its plan (ValidationJob's validator)
    try:
        result = rollout.result.result(timeout=0) if rollout.result.done() else None
    except Exception:
        result = None
    if not isinstance(result, ValidationResult):
        return RolloutPreview(plan=plan)
    path: ObjectPath | None = result.object_paths[0] if result.object_paths else None
    return RolloutPreview(
        plan=plan, object_path=path,
        goal_error_m=None if result.goal_error_m is None else float(result.goal_error_m.to_numpy()[0]),
        collision_cost=None if result.collision_cost is None else float(result.collision_cost.to_numpy()[0]),
        obstacle_contact=bool(result.obstacle_contact.to_numpy()[0]) if result.obstacle_contact is not None else False,
        success=bool(result.success.to_numpy()[0]))


def _is_prefix(rolled: Plan, executed: Plan) -> bool:
    """Whether `executed` begins with `rolled`'s waypoints (the chosen plan is its rollout plus the way back)."""
    a, b = rolled.positions.to_numpy(), executed.positions.to_numpy()
    return a.shape[1] == b.shape[1] and a.shape[0] <= b.shape[0] and bool(np.allclose(a, b[: a.shape[0]]))


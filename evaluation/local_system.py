"""The push pipeline's services in this process, for evaluation: same algorithms, no bus.

An evaluation runs thousands of push requests; each worker process holds its own pipeline wired to
in-process services — the sampler service's handler, the validator's arm rollout, and a simulated
robot bridge (`SimExecutor`, with its limit checks) — so the measured behaviour is the system's,
without a router in the loop. The pose source is pluggable (`PoseSource`), which is how the
baselines that have no service of their own (the grasp-pose baseline) enter the same pipeline.

The simulated bridge here also watches the object against the obstacles while a plan runs (the
bus bridge reports robot contacts only); multi-step evaluation needs both. It executes in the
trial's execution world (`LocalRobot.execution_world`, `shared.sim.world`): physics and an object
pose the planner was not told.
"""
from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field, replace

import numpy as np

from services.planner.cancellation import Cancellation
from services.planner.outcome import Execution, PushError
from services.planner.pipeline import PushPipeline, PushServices
from services.planner.stages import PipelineSettings
from services.robot_bridge.sim_backend import SimBackend, SimExecutor
from services.sampler.service import SamplerService
from services.validator.service import validate
from shared.bus.errors import ServiceError
from shared.messages import ExecutionState, ObjectRef, Plan, SampleRequest, SampleResponse, SimWorld, ValidationJob
from shared.push_outcome import object_pose
from shared.sim.world import ExecutionWorld, PoseError

REALTIME_FACTOR = 1000.0  # as the planner service asks of the simulated bridge: as fast as physics runs

PoseSource = Callable[[SampleRequest], SampleResponse]


@dataclass
class Contacts:
    """What touched an obstacle during the executions since the last `reset()`."""

    robot_obstacle: set[str] = field(default_factory=set)  # robot link names
    object_obstacle: bool = False

    def reset(self) -> None:
        self.robot_obstacle.clear()
        self.object_obstacle = False

    @property
    def any(self) -> bool:
        return bool(self.robot_obstacle) or self.object_obstacle


class LocalRobot:
    """Simulated robots (one per arm + hand) executing plans in this process."""

    def __init__(self):
        self._executors: dict[tuple[str, str], SimExecutor] = {}
        self.contacts = Contacts()
        # The world a reset builds: the physics the robot meets and the object's true pose (None: the
        # planner's own world). Set per trial by the evaluation; the planner never sees it.
        self.execution_world: ExecutionWorld | None = None
        # The true object and its true pose (T_world_O), when the planner plans around something else (a
        # reconstruction from a camera cloud): a reset puts this object there. None: the planner's object.
        self.true_object: tuple[ObjectRef, np.ndarray] | None = None

    def executor(self, arm: str, hand: str) -> SimExecutor:
        key = (arm, hand)
        if key not in self._executors:
            backend = SimBackend(arm, hand)
            backend.publish = lambda _state, backend=backend: self._watch_object(backend)
            backend.connect()
            self._executors[key] = SimExecutor(backend)
        return self._executors[key]

    def execute(self, plan: Plan, world: SimWorld | None, cancel: Cancellation | None = None) -> Execution:
        executor = self.executor(plan.arm, plan.hand)
        if world is not None:
            executor.backend.reset_world(*self._true_world(world))
        stop = threading.Event()
        unregister = cancel.on_cancel(stop.set) if cancel is not None else (lambda: None)
        try:
            state: ExecutionState = executor.execute(plan, REALTIME_FACTOR, stop=stop)
        finally:
            unregister()
        self.contacts.robot_obstacle.update(link for link, other in executor.backend.collisions if other.startswith("obstacle"))
        return Execution(final=state)

    def _true_world(self, told: SimWorld) -> tuple[SimWorld, ExecutionWorld | None]:
        """The world a reset builds from what the planner sent: the true object at its true pose, when known
        (its pose error is then already applied)."""
        if self.true_object is None:
            return told, self.execution_world
        obj, T_world_O = self.true_object
        world = SimWorld(object=obj, object_pose=object_pose(T_world_O), obstacles=told.obstacles)
        execution = None if self.execution_world is None else replace(self.execution_world, pose_error=PoseError())
        return world, execution

    def _watch_object(self, backend: SimBackend) -> None:
        """Called at the state rate during execution: does the object touch an obstacle?"""
        if backend.scene is not None and not self.contacts.object_obstacle:
            self.contacts.object_obstacle = backend.scene.object_touches_obstacle()

    def close(self) -> None:
        for executor in self._executors.values():
            executor.backend.disconnect()
        self._executors.clear()


def validate_here(job: ValidationJob) -> Future:
    """The validator farm's job, run in this process before returning (the future is already done)."""
    future: Future = Future()
    try:
        future.set_result(validate(job))
    except ServiceError as exc:
        future.set_exception(exc)
    return future


def sampler_source(service: SamplerService) -> PoseSource:
    """The sampler service's handler as a pose source (service errors become PushErrors, as over the bus)."""

    def sample(request: SampleRequest) -> SampleResponse:
        try:
            return service.handle(request)
        except ServiceError as exc:
            raise PushError(exc.code, f"sampler: {exc}") from exc

    return sample


class LocalSystem:
    """A push pipeline per pose source, sharing one simulated robot."""

    def __init__(self, settings: PipelineSettings = PipelineSettings()):
        self.settings = settings
        self.robot = LocalRobot()
        self.sampler = SamplerService()
        self._pipelines: dict[str, PushPipeline] = {}

    def pipeline(self, source_name: str, source: PoseSource | None = None) -> PushPipeline:
        """The pipeline whose pose source is `source` (default: the sampler service)."""
        if source_name not in self._pipelines:
            services = PushServices(sample=source or sampler_source(self.sampler), validate=validate_here,
                                    execute=self.robot.execute)
            self._pipelines[source_name] = PushPipeline(services, self.settings)
        return self._pipelines[source_name]

    def close(self) -> None:
        for pipeline in self._pipelines.values():
            pipeline.close()
        self.robot.close()
        self.sampler.close()

"""Validation of pose batches: push every pose, augment the successes, push the copies too.

Plain module (no Zenoh): the bus service, the CLI and the benchmarks all call `Validator`.
A `Validator` keeps the most recently used `PushSimulator`s (one PyBullet scene per object, hand
and physics) so consecutive jobs on the same object skip the scene build.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from shared.robots.hands import HandModel
from shared.validation.augment import COPIES_PER_SUCCESS, halton_perturbations
from shared.validation.push import DEFAULT_PUSH_DISTANCE_M, PushOutcome, PushSimulator, TableObject
from shared.world.sim import PhysicsParams

PLACEMENT_NOISE_XY_M = 0.005  # trials: object centre moved within this radius ...
PLACEMENT_NOISE_YAW_DEG = 5.0  # ... and turned about the vertical by up to this angle
_CACHED_SCENES = 2

Progress = Callable[[int], None]


@dataclass
class AugmentedRun:
    """Perturbed copies of successful poses and their outcomes."""

    poses: np.ndarray  # [M, 25]
    parent_index: np.ndarray  # [M] index of the parent in the validated batch
    outcomes: list[PushOutcome] = field(default_factory=list)


@dataclass
class ValidationRun:
    """Outcomes of one batch, in pose order; `augmented` when augmentation was asked for."""

    outcomes: list[PushOutcome]
    augmented: AugmentedRun | None = None


def augmentation_seed(seed: int, parent_index: int) -> int:
    """Per-parent Halton seed: copies differ between parents yet are reproducible from the job seed."""
    return int(np.random.SeedSequence([seed, parent_index]).generate_state(1)[0])


def placement_offsets(trials: int, seed: int) -> np.ndarray:
    """[trials, 4, 4] object placement noise in D: a yaw about the object's vertical axis and a shift.

    Trial t's offset depends only on (seed, t), so a run with more trials extends a shorter one.
    The offsets are applied to the resting pose, whose centre of mass sits above D's origin, so the
    yaw turns the object about its own centre and it stays on the table.
    """
    out = np.tile(np.eye(4), (trials, 1, 1))
    for trial, offset in enumerate(out):
        rng = np.random.default_rng(np.random.SeedSequence([seed, trial]))
        yaw = math.radians(rng.uniform(-PLACEMENT_NOISE_YAW_DEG, PLACEMENT_NOISE_YAW_DEG))
        radius = PLACEMENT_NOISE_XY_M * math.sqrt(rng.uniform())
        angle = rng.uniform(0.0, 2.0 * math.pi)
        offset[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        offset[:2, 3] = [radius * math.cos(angle), radius * math.sin(angle)]
    return out


class Validator:
    """Runs push validations; holds a few PyBullet scenes for reuse. Not thread-safe: one per thread."""

    def __init__(self, params: PhysicsParams | None = None):
        self.default_params = params or PhysicsParams()
        # (object id, URDF, T_D_O bytes, hand, physics)
        self._simulators: OrderedDict[tuple[str, Path, bytes, str, PhysicsParams], PushSimulator] = OrderedDict()

    def close(self) -> None:
        while self._simulators:
            self._simulators.popitem()[1].close()

    def __enter__(self) -> Validator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def validate(
        self,
        obj: TableObject,
        hand: HandModel,
        poses: np.ndarray,
        *,
        params: PhysicsParams | None = None,
        push_distance_m: float = DEFAULT_PUSH_DISTANCE_M,
        augment: bool = False,
        seed: int = 0,
        object_offsets: Sequence[np.ndarray | None] | None = None,
        progress: Progress | None = None,
    ) -> ValidationRun:
        """Push each pose; with `augment`, also push `COPIES_PER_SUCCESS` Halton copies of each success.

        `object_offsets[i]` (4x4 in D, or None) moves the object before pose i (placement noise).
        `progress(k)` is called after every k episodes.
        """
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 25)
        sim = self._simulator(obj, hand, params or self.default_params)
        offsets = object_offsets if object_offsets is not None else [None] * len(poses)
        outcomes = [self._run(sim, pose, push_distance_m, offset, progress)
                    for pose, offset in zip(poses, offsets, strict=False)]
        run = ValidationRun(outcomes)
        if augment:
            run.augmented = self._augment(sim, hand, poses, outcomes, push_distance_m, seed, progress)
        return run

    def _augment(self, sim: PushSimulator, hand: HandModel, poses: np.ndarray, outcomes: list[PushOutcome],
                 push_distance_m: float, seed: int, progress: Progress | None) -> AugmentedRun:
        lower, upper = hand.joint_lower.double().numpy(), hand.joint_upper.double().numpy()
        parents = [i for i, outcome in enumerate(outcomes) if outcome.success]
        copies = [halton_perturbations(poses[i], COPIES_PER_SUCCESS, augmentation_seed(seed, i), lower, upper)
                  for i in parents]
        run = AugmentedRun(
            poses=np.concatenate(copies) if copies else np.zeros((0, 25)),
            parent_index=np.repeat(np.asarray(parents, dtype=np.int64), COPIES_PER_SUCCESS))
        run.outcomes = [self._run(sim, pose, push_distance_m, None, progress) for pose in run.poses]
        return run

    @staticmethod
    def _run(sim: PushSimulator, pose: np.ndarray, distance: float, offset: np.ndarray | None,
             progress: Progress | None) -> PushOutcome:
        outcome = sim.run(pose, distance, offset)
        if progress is not None:
            progress(1)
        return outcome

    def _simulator(self, obj: TableObject, hand: HandModel, params: PhysicsParams) -> PushSimulator:
        key = (obj.object_id, obj.urdf_path, obj.transform_d.tobytes(), hand.name, params)
        sim = self._simulators.pop(key, None)
        if sim is None:
            sim = PushSimulator(hand, obj, params)
            while len(self._simulators) >= _CACHED_SCENES:
                self._simulators.popitem(last=False)[1].close()
        self._simulators[key] = sim  # most recently used last
        return sim

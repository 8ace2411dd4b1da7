"""Labelled diffusion samples for the success critic: what the planner's prescreen measures, recorded.

    gd2p critic data --objects 400 --out data/critic-allegro

For each training object (the data engine's fixed hash order over the train split), one push frame:
the object in its default resting pose, turned about z by a yaw drawn from the object's seed, pushed
along +x of D (in D only that yaw matters). The sampler draws K = 200 poses (DDPM, the planner's
default) as it would for a push request; `per_object` of them, drawn at random, are pushed 20 cm by
the validator's floating hand (the prescreen's push) and judged by the one push judge. A record per
object holds the yaw, the pushed poses and their outcomes (success, position error); the BPS is not
stored but recomputed from (object, yaw) by the sampler's own encoder when training, so training
and inference cannot encode an object differently.

Records go to a keyed, fsynced JSON-lines store (`evaluation.store.ResultStore`): a killed build
loses at most the objects in flight, and a restarted one skips the objects it has. Objects run in
spawn worker processes, each with its own sampler service and validator.
"""
from __future__ import annotations

import hashlib
import multiprocessing as mp
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from evaluation.store import ResultStore

if TYPE_CHECKING:
    from shared.sampling.server import SamplerService

K_SAMPLES = 200  # as a push request (PlannerOptions.k)
PUSH_DISTANCE_M = 0.20

_sampler: SamplerService | None = None  # each worker's


@dataclass(frozen=True)
class CriticObject:
    """One object's unit of work: sample in a frame turned by `yaw_deg`, push `per_object` of the samples."""

    object_id: str
    hand: str
    yaw_deg: float
    per_object: int
    seed: int

    @property
    def key(self) -> str:
        return f"{self.hand}/{self.object_id}"


def object_seed(object_id: str, seed: int) -> int:
    digest = hashlib.sha256(f"gd2p-critic:{seed}:{object_id}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & (2**31 - 1)


def plan_objects(object_ids: list[str], hand: str, per_object: int, seed: int) -> list[CriticObject]:
    """The units of work: one frame per object, its yaw drawn from the object's own seed."""
    units = []
    for object_id in object_ids:
        rng = np.random.default_rng(object_seed(object_id, seed))
        units.append(CriticObject(object_id, hand, float(rng.uniform(-180.0, 180.0)), per_object,
                                  object_seed(object_id, seed)))
    return units


def label_object(unit: CriticObject) -> dict[str, Any]:
    """Sample, push a random subset of the samples, and record the outcomes (runs in a worker)."""
    from shared.contracts.messages import ObjectRef, SampleRequest, ValidationJob
    from shared.sampling.critic_train import critic_frame
    from shared.validation.jobs import validate

    assert _sampler is not None  # set by _init_worker
    frame = critic_frame(unit.object_id, unit.yaw_deg)
    ref = ObjectRef(library_id=unit.object_id)
    reply = _sampler.handle(SampleRequest(object=ref, hand=unit.hand, frame=frame, k=K_SAMPLES, seed=unit.seed,
                                          score=False))
    poses = reply.poses_d.to_numpy().astype(np.float64)
    chosen = np.random.default_rng(unit.seed).choice(len(poses), size=min(unit.per_object, len(poses)), replace=False)
    result = validate(ValidationJob(object=ref, hand=unit.hand, poses=poses[chosen], frame=frame,
                                    push_distance_m=PUSH_DISTANCE_M, seed=unit.seed))
    return {**asdict(unit), "checkpoint_id": reply.checkpoint_id, "poses_d": np.round(poses[chosen], 6).tolist(),
            "success": result.success.to_numpy().astype(bool).tolist(),
            "position_error_m": np.round(result.position_error_m.to_numpy(), 5).tolist()}


def _init_worker() -> None:
    import torch

    torch.set_num_threads(1)
    global _sampler
    from shared.sampling.server import SamplerService

    _sampler = SamplerService()


def _keyed(unit: CriticObject) -> tuple[str, dict[str, Any]]:
    return unit.key, label_object(unit)


def build(out: Path, object_ids: list[str], hand: str = "allegro", per_object: int = 32, seed: int = 0,
          workers: int = 2) -> ResultStore:
    """Label every object of `object_ids` not yet in `out` (resumable); the store."""
    store = ResultStore(out, {"hand": hand, "per_object": per_object, "seed": seed, "k": K_SAMPLES,
                              "push_distance_m": PUSH_DISTANCE_M})
    todo = [u for u in plan_objects(object_ids, hand, per_object, seed) if u.key not in store.records]
    with tqdm(total=len(object_ids), initial=len(object_ids) - len(todo), desc="critic data", unit="object") as bar:
        if workers <= 1:
            _init_worker()
            results = map(_keyed, todo)
            _consume(results, store, bar)
        else:
            with mp.get_context("spawn").Pool(workers, initializer=_init_worker) as pool:
                _consume(pool.imap_unordered(_keyed, todo), store, bar)
    return store


def _consume(results, store: ResultStore, bar) -> None:
    pushed = successes = 0
    for key, record in results:
        store.add(key, record)
        pushed += len(record["success"])
        successes += sum(record["success"])
        bar.set_postfix(pushes=pushed, success=f"{successes / max(pushed, 1):.0%}")
        bar.update()

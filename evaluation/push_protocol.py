"""The paper's real-robot protocol, in simulation: methods × objects × directions × trials, with the arm.

Protocol (paper, "Experiment Protocol and Evaluation"): 14 test objects — 8 procedural objects
standing in for the 3D-printed set and 6 everyday-like objects, none of them trained on — 3
directions evenly spread around a circle, one of them the pull toward the robot (180°), 5 trials
per direction with the object placed again each time (a few mm and degrees of placement noise, as a
person re-placing it), a 0.20 m push planned and executed with the arm. A trial succeeds when the
object's centre ends within 0.03 m of the target, it turned ≤ 45° and did not topple
(`shared.push_outcome.judge_push`); "–" marks a trial with no kinematically feasible plan, counted
as a failure. The hand keeping contact throughout is not judged separately: a 0.20 m push that ends
within 3 cm of its target has kept the object in front of the hand.

Methods (the paper's, on one pipeline — only the pose source and the choice among plans differ):
- `gd2p`: K = 200 diffusion samples, plans ranked by arm rollouts (V = α L_goal + β L_coll + γ L_dir);
- `gd2p-no-ranking`: the same samples, a random feasible plan executed;
- `nearest`: the nearest training object's stored poses (BPS), a random feasible plan (as the paper);
- `fixed`: the spatula pose behind the object;
- `grasp`: grasp-only optimiser poses (`grasp_baseline.py`), a feasible one of the best executed.

Episodes run in spawn worker processes, each with its own in-process system (`local_system.py`);
every finished episode is recorded at once, so a killed run resumes where it stopped.
"""
from __future__ import annotations

import hashlib
import math
import multiprocessing as mp
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from shared.frames import make_transform, yaw_rotation
from shared.messages import ObjectRef, PushRequest
from shared.objects import load_object, split_of
from shared.push_outcome import object_pose

PROCEDURAL_OBJECTS = ("proc-box-000", "proc-box-001", "proc-box-002", "proc-cylinder-000", "proc-cylinder-001",
                      "proc-ellipsoid-001", "proc-cone-000", "proc-hull-001")
EVERYDAY_OBJECTS = ("pb-duck", "pb-mug", "pb-teddy", "pb-jenga", "pb-toy-prism", "pb-toy-cylinder")
DIRECTIONS_DEG = (60.0, 180.0, 300.0)  # evenly spread; 180° pulls the object toward the robot
TRIALS = 5
PUSH_DISTANCE_M = 0.20
OBJECT_XY = (0.40, 0.0)  # in front of the robot, where both arms reach all three directions (pulls fail at 0.5 m)
PLACEMENT_NOISE_M = 0.01  # uniform in a ±1 cm square
PLACEMENT_NOISE_DEG = 5.0  # uniform yaw in ±5°
METHODS = ("gd2p", "gd2p-no-ranking", "nearest", "fixed", "grasp")
ROBOTS = {"allegro": "panda", "leap": "xarm7"}


@dataclass(frozen=True)
class Episode:
    method: str
    hand: str
    object_id: str
    direction_deg: float
    trial: int

    @property
    def key(self) -> str:
        return f"{self.method}/{self.hand}/{self.object_id}/{self.direction_deg:g}/{self.trial}"

    @property
    def arm(self) -> str:
        return ROBOTS[self.hand]

    @property
    def seed(self) -> int:
        """The same placement and sampler seed for every method: methods face identical trials."""
        digest = hashlib.sha256(f"{self.object_id}/{self.direction_deg:g}/{self.trial}".encode()).digest()
        return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


def episodes(methods: Sequence[str], hand: str, objects: Sequence[str], directions: Sequence[float],
             trials: int) -> list[Episode]:
    for object_id in objects:
        if split_of(object_id) != "test":
            raise ValueError(f"{object_id} is in the {split_of(object_id)} split; evaluation uses test objects only")
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise ValueError(f"unknown method(s) {sorted(unknown)}; known: {', '.join(METHODS)}")
    return [Episode(m, hand, o, d, t) for m in methods for o in objects for d in directions for t in range(trials)]


def placement(episode: Episode) -> np.ndarray:
    """T_world_O of the episode's trial: resting at the spot in front of the robot, re-placed with noise."""
    rng = np.random.default_rng(episode.seed)
    dx, dy = rng.uniform(-PLACEMENT_NOISE_M, PLACEMENT_NOISE_M, 2)
    yaw = math.radians(rng.uniform(-PLACEMENT_NOISE_DEG, PLACEMENT_NOISE_DEG))
    obj = load_object(episode.object_id)
    return make_transform(yaw_rotation(yaw), np.array([OBJECT_XY[0] + dx, OBJECT_XY[1] + dy, 0.0])) @ obj.T_D_O()


def push_request(episode: Episode, k: int = 200) -> PushRequest:
    method = {"gd2p-no-ranking": "gd2p", "grasp": "gd2p"}.get(episode.method, episode.method)
    ranking = episode.method == "gd2p"  # the paper: NN and w/o ranking execute a random feasible plan
    return PushRequest(object=ObjectRef(library_id=episode.object_id), object_pose=object_pose(placement(episode)),
                       direction_deg=episode.direction_deg, distance_m=PUSH_DISTANCE_M, hand=episode.hand,
                       arm=episode.arm, k=k, ranking=ranking, method=method, seed=episode.seed)


# ------------------------------------------------------------------------------------------ workers

_system = None
_grasp = None


def _init_worker(grasp_cache: str) -> None:
    import torch

    torch.set_num_threads(1)
    global _system, _grasp
    from evaluation.grasp_baseline import GraspPoseSource
    from evaluation.local_system import LocalSystem

    _system = LocalSystem()
    _grasp = GraspPoseSource(grasp_cache)


def run_episode(episode: Episode) -> dict[str, Any]:
    """Plan and execute one trial; a record with the outcome ("infeasible" when no plan exists)."""
    from services.planner.outcome import PushError

    started = time.perf_counter()
    source = _grasp if episode.method == "grasp" else None
    pipeline = _system.pipeline(episode.method if source is not None else "sampler", source)
    record: dict[str, Any] = {**asdict(episode), "seed": episode.seed}
    try:
        response = pipeline.run(push_request(episode)).response
    except PushError as exc:
        record.update(outcome="infeasible" if exc.code == "infeasible" else "error", success=False,
                      error_code=exc.code, message=exc.message[:300])
    except Exception as exc:  # a crash in one trial is recorded, not fatal to the evaluation
        record.update(outcome="error", success=False, error_code="internal", message=repr(exc)[:300])
    else:
        result = response.result
        record.update(outcome="success" if response.success else "failure", success=bool(response.success),
                      position_error_m=result.position_error_m, rotation_deg=result.rotation_deg,
                      toppled=result.toppled, timings_s={k: round(v, 3) for k, v in response.timings_s.items()})
        if response.score is not None:  # what the chosen plan's arm rollout predicted (ranking's L_goal)
            record["predicted_l_goal"] = round(response.score.l_goal, 4)
    record["seconds"] = round(time.perf_counter() - started, 2)
    return record


def _keyed(job: tuple[Callable[[Any], dict[str, Any]], Any]) -> tuple[str, dict[str, Any]]:
    work, item = job
    return item.key, work(item)


def run_in_workers(items: Sequence[Any], work: Callable[[Any], dict[str, Any]], store, workers: int,
                   grasp_cache: Path, label: str) -> None:
    """`work(item)` for every item (each with a `.key`) over `workers` spawn processes, each record
    stored as soon as it arrives (resumable); a progress bar shows the live success rate."""
    if not items:
        return
    grasp_cache.mkdir(parents=True, exist_ok=True)
    jobs = [(work, item) for item in items]
    with tqdm(total=len(items), desc=label, unit="trial") as bar:
        if workers <= 1:
            _init_worker(str(grasp_cache))
            _consume(map(_keyed, jobs), store, bar)
            return
        context = mp.get_context("spawn")
        with context.Pool(workers, initializer=_init_worker, initargs=(str(grasp_cache),)) as pool:
            _consume(pool.imap_unordered(_keyed, jobs), store, bar)


def _consume(results, store, bar) -> None:
    done = successes = 0
    for key, record in results:
        store.add(key, record)
        done += 1
        successes += int(record["success"])
        bar.set_postfix(success=f"{successes / done:.0%}", last=f"{record['object_id']}:{record['outcome']}")
        bar.update()

"""Can the success critic order a request's poses as the prescreen's pushes do? (issue 50)

    python bench/critic_ranking.py --json          # val requests; fine-tuned on train-split requests

The prescreen (`shared.planning.stages.prescreen`) pushes the first 24 feasible poses of a request (the critic's
order) with the validator's floating hand and plans those that passed first, closest to the target first: about
2 of a request's 4.4 validator CPU seconds (bench/push.py's `cpu_s_per_request`). A critic that ordered poses as
well would make those pushes unnecessary. Measured here, per request of the protocol's directions:

1. the request is planned with the default settings up to its first arm rollout, but with the critic's first
   `PUSHED` (48) feasible poses pushed, not 24, so that an order other than the critic's has the truth for the
   poses it would put first (each request's record is kept in `--store`: a rerun resumes);
2. each order's first `max_plans` (6) poses, the plans a request rolls out, are read against that truth:
   the share that pass (`top_pass`), their mean distance from the target (`top_error_cm`, a miss counted at most
   10 cm), the first pose's (`first_pass`, `first_error_cm`), and how the critic's predicted error ranks the
   true one within a request (`spearman`, median over requests). Orders:
   - `prescreen`: the planner's (the passed poses among the first 24, closest first);
   - `critic`: the critic's P(success), the planner's order without a prescreen;
   - `critic_error`: the critic's own predicted position error (its second head), lowest first;
   - `tuned_error`: that head fine-tuned on requests of `--train-objects` train-split objects (a listwise loss
     on each request's true errors, `fine_tune`), then read on the val requests it never saw;
   - `oracle`: the best the 48 pushed poses hold.
3. `learning_curve`: `tuned_error` again with the first third and two thirds of the train objects, then all of
   them: whether more such requests would close the gap.

Val objects, as every tuning measurement (docs/evaluation.md); the critic is the shipped one. The requests are
planned, never executed.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import multiprocessing as mp
import sys
import time
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.contracts.messages import ObjectRef, PushRequest, ValidationJob, ValidationResult

if TYPE_CHECKING:
    from evaluation.local_system import LocalSystem
    from shared.sampling.critic import SuccessCritic
    from shared.sampling.server import SamplerService

PUSHED = 48  # poses of each request pushed: the prescreen's 24 and as many more
MISS_CAP_M = 0.10  # a miss counts at most this far in the mean error (a pose that sent the object away)
HAND = "allegro"
TRAIN_SEED = 7  # which train-split objects the fine-tune reads

_system: LocalSystem | None = None  # each worker's


@dataclass(frozen=True)
class Unit:
    object_id: str
    direction_deg: float

    @property
    def key(self) -> str:
        return f"{self.object_id}/{self.direction_deg:g}"


class Planned(Exception):
    """Raised at a request's first arm rollout: what the bench needs has been pushed by then."""


@dataclass
class StopAtRollout:
    """The pipeline's `validate`: runs the floating-hand (prescreen) jobs here and keeps them with their results;
    stops the request at its first arm rollout."""

    jobs: list[tuple[ValidationJob, ValidationResult]] = dataclasses.field(default_factory=list)

    def __call__(self, job: ValidationJob) -> Future[ValidationResult]:
        from evaluation.local_system import validate_here

        if job.with_arm:
            raise Planned
        future = validate_here(job)
        if future.exception() is None:
            self.jobs.append((job, future.result()))
        return future


def _init_worker() -> None:
    global _system
    from evaluation.local_system import LocalSystem
    from shared.planning.stages import PipelineSettings

    torch.set_num_threads(1)
    _system = LocalSystem(dataclasses.replace(PipelineSettings(), prescreen=PUSHED))


def label_request(unit: Unit) -> tuple[str, dict[str, Any]]:
    """The request planned up to its first rollout: the pushed poses in D, their frame and their outcomes."""
    from evaluation.local_system import sampler_source
    from shared.planning.pipeline import PushPipeline, PushServices

    assert _system is not None
    recorder = StopAtRollout()

    def refuse(*_args: object) -> Any:
        raise Planned

    pipeline = PushPipeline(PushServices(sample=sampler_source(_system.sampler), validate=recorder, execute=refuse),
                            _system.settings)
    try:
        pipeline.run(PushRequest(object=ObjectRef(library_id=unit.object_id), direction_deg=unit.direction_deg))
    except Exception:  # Planned, or no feasible pose: what was pushed is what counts
        pass
    finally:
        pipeline.close()
    if not recorder.jobs:
        return unit.key, {"object": unit.object_id, "direction_deg": unit.direction_deg, "pushed": 0}
    frame = recorder.jobs[0][0].frame
    assert frame is not None  # the prescreen pushes in the request's frame
    success = np.concatenate([r.success.to_numpy() for _, r in recorder.jobs]).astype(bool)
    error = np.concatenate([r.position_error_m.to_numpy() for _, r in recorder.jobs]).astype(np.float64)
    return unit.key, {"object": unit.object_id, "direction_deg": unit.direction_deg, "pushed": int(success.size),
                      "frame": frame.model_dump(mode="json"),
                      "poses": np.concatenate([j.poses.to_numpy() for j, _ in recorder.jobs]).tolist(),
                      "success": success.tolist(), "error_m": error.tolist()}


def collect(store_dir: Path, units: list[Unit], workers: int) -> list[dict[str, Any]]:
    """Every unit's record, labelling those `store_dir` does not hold yet (resumable)."""
    from tqdm import tqdm

    from evaluation.store import ResultStore

    store = ResultStore(store_dir, {"pushed": PUSHED, "hand": HAND})
    todo = [u for u in units if not store.done(u.key)]
    with tqdm(total=len(units), initial=len(units) - len(todo), desc=store_dir.name, unit="request") as bar:
        with mp.get_context("spawn").Pool(workers, initializer=_init_worker) as pool:
            for key, record in pool.imap_unordered(label_request, todo):
                store.add(key, record)
                bar.update()
    return [store.records[u.key] for u in units if store.records[u.key]["pushed"] > 0]


@dataclass(frozen=True)
class Group:
    """One request's pushed poses as the critic reads them, and their truth."""

    object_id: str
    poses: torch.Tensor
    bps: torch.Tensor
    contact: torch.Tensor | None
    success: torch.Tensor
    error_m: torch.Tensor  # capped at MISS_CAP_M


def groups_of(records: list[dict[str, Any]], critic: SuccessCritic, service: SamplerService) -> list[Group]:
    """The critic's inputs for each record's poses: the object encoded as the sampler service encodes it."""
    from shared.contracts.messages import DirectionFrame
    from shared.robots.hands import load_hand
    from shared.sampling.critic_features import contact_features
    from shared.sampling.server import object_input

    sampler, hand = service.sampler(HAND), load_hand(HAND)
    groups = []
    for r in records:
        frame = DirectionFrame.model_validate(r["frame"])
        points, _, label = sampler.points_in_d(object_input(ObjectRef(library_id=r["object"])), frame)
        points_t = torch.as_tensor(np.asarray(points, dtype=np.float32))
        poses = torch.as_tensor(np.asarray(r["poses"], dtype=np.float32))
        groups.append(Group(r["object"], poses,
                            torch.as_tensor(np.asarray(sampler.encode_points(points, label), dtype=np.float32))[None],
                            contact_features(hand, poses, points_t) if critic.uses_contact else None,
                            torch.tensor(r["success"], dtype=torch.float32),
                            torch.tensor(np.minimum(r["error_m"], MISS_CAP_M), dtype=torch.float32)))
    return groups


def orders(group: Group, critic: SuccessCritic, prescreened: int) -> dict[str, np.ndarray]:
    """The poses of a request (indices into its pushed poses) in each order but the fine-tuned one."""
    success, error = group.success.numpy().astype(bool), group.error_m.numpy()
    first = np.arange(min(prescreened, len(success)))
    passed = first[success[first]]
    with torch.no_grad():
        _, log_error = critic(group.poses, group.bps, None, group.contact)
    oracle = np.concatenate([np.flatnonzero(success)[np.argsort(error[success], kind="stable")],
                             np.flatnonzero(~success)])
    return {"prescreen": np.concatenate([passed[np.argsort(error[passed], kind="stable")], first[~success[first]]]),
            "critic": np.arange(len(success)), "critic_error": np.argsort(log_error.numpy(), kind="stable"),
            "oracle": oracle}


def figures(groups: list[Group], chosen: list[np.ndarray], predicted: list[np.ndarray] | None, top: int) -> dict[str, Any]:
    """How good each request's first `top` poses of an order are, in truth (see the module's doc)."""
    rows = [(g.success.numpy()[o[:top]].mean(), g.error_m.numpy()[o[:top]].mean(), g.success.numpy()[o[0]],
             g.error_m.numpy()[o[0]]) for g, o in zip(groups, chosen, strict=True)]
    top_pass, top_error, first_pass, first_error = np.array(rows, dtype=np.float64).mean(axis=0)
    out: dict[str, Any] = {"top_pass": round(top_pass, 3), "top_error_cm": round(100 * top_error, 2),
                           "first_pass": round(first_pass, 3), "first_error_cm": round(100 * first_error, 2)}
    if predicted is not None:
        rho = [spearmanr(p, g.error_m.numpy()).statistic for g, p in zip(groups, predicted, strict=True) if len(p) > 5]
        out["spearman"] = round(float(np.nanmedian(rho)), 3)
    return out


def predicted_errors(groups: list[Group], critic: SuccessCritic) -> list[np.ndarray]:
    with torch.no_grad():
        return [critic(g.poses, g.bps, None, g.contact)[1].numpy() for g in groups]


def fine_tune(groups: list[Group], critic: SuccessCritic, steps: int = 300, learning_rate: float = 3e-4,
              tau_m: float = 0.01, batch: int = 16, seed: int = 0) -> SuccessCritic:
    """A copy of `critic` trained on requests: ListNet on its error head (each request's poses softmax-weighted by
    their true error, tau_m wide) and binary cross-entropy on its success head, which the planner also reads."""
    torch.manual_seed(seed)
    model = copy.deepcopy(critic).train()
    optimiser = torch.optim.AdamW(model.parameters(), lr=learning_rate, weight_decay=0.01)
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        loss = torch.zeros(())
        for i in rng.choice(len(groups), size=min(batch, len(groups)), replace=False):
            g = groups[i]
            logits, log_error = model(g.poses, g.bps, None, g.contact)
            target = torch.softmax(-g.error_m / tau_m, dim=0)
            loss = loss - (target * torch.log_softmax(-log_error, dim=0)).sum() \
                + torch.nn.functional.binary_cross_entropy_with_logits(logits, g.success)
        optimiser.zero_grad()
        (loss / batch).backward()
        optimiser.step()
    return model.eval()


def train_objects(count: int) -> list[str]:
    from shared.world.objects.catalog import list_object_ids

    ids = list_object_ids("train")
    return [ids[i] for i in np.random.default_rng(TRAIN_SEED).choice(len(ids), size=min(count, len(ids)), replace=False)]


def run(args: argparse.Namespace) -> dict[str, Any]:
    from evaluation.methods import VAL_OBJECTS
    from evaluation.push_protocol import DIRECTIONS_DEG
    from evaluation.report import code_version, machine
    from shared.planning.stages import PipelineSettings
    from shared.sampling.server import SamplerService

    settings = PipelineSettings()
    val_objects = args.val_objects.split(",") if args.val_objects else list(VAL_OBJECTS)
    val = collect(args.store / "val", [Unit(o, d) for o in val_objects for d in DIRECTIONS_DEG], args.workers)
    train = collect(args.store / "train", [Unit(o, d) for o in train_objects(args.train_objects)
                                           for d in DIRECTIONS_DEG], args.workers)
    service = SamplerService()
    critic = service.critic(HAND, service.sampler(HAND))
    if critic is None:
        raise SystemExit(f"no {HAND} success critic is installed for the shipped sampler checkpoint")
    critic.eval()
    val_groups, train_groups = groups_of(val, critic, service), groups_of(train, critic, service)
    top = settings.max_plans
    by_order = [orders(g, critic, settings.prescreen) for g in val_groups]
    shipped_predicted = predicted_errors(val_groups, critic)
    results = {name: figures(val_groups, [o[name] for o in by_order],
                             shipped_predicted if name == "critic_error" else None, top)
               for name in ("prescreen", "critic", "critic_error", "oracle")}
    started = time.perf_counter()
    results["tuned_error"] = tuned_figures(train_groups, critic, val_groups, top)
    tune_s = time.perf_counter() - started
    # The same fine-tune on a third and two thirds of the train objects: whether more requests would close the gap.
    objects = list(dict.fromkeys(g.object_id for g in train_groups))
    curve = []
    for count in (len(objects) // 3, 2 * len(objects) // 3):
        subset = [g for g in train_groups if g.object_id in set(objects[:count])]
        curve.append({"train_objects": count, "train_requests": len(subset)} | tuned_figures(subset, critic, val_groups, top))
    curve.append({"train_objects": len(objects), "train_requests": len(train_groups)} | results["tuned_error"])
    return {"command": "python bench/critic_ranking.py " + " ".join(sys.argv[1:]), "date": time.strftime("%Y-%m-%d"),
            "code": code_version(), "machine": machine(), "pushed_per_request": PUSHED, "top": top,
            "val_requests": len(val_groups), "val_objects": len({g.object_id for g in val_groups}),
            "train_requests": len(train_groups), "train_objects": len({g.object_id for g in train_groups}),
            "fine_tune_s": round(tune_s, 1), "learning_curve": curve, "orders": results}


def tuned_figures(train_groups: list[Group], critic: SuccessCritic, val_groups: list[Group], top: int) -> dict[str, Any]:
    """The val requests in the order of the critic's error head fine-tuned on `train_groups`."""
    predicted = predicted_errors(val_groups, fine_tune(train_groups, critic))
    return figures(val_groups, [np.argsort(p, kind="stable") for p in predicted], predicted, top)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--store", type=Path, default=Path("data/bench-critic-ranking"),
                        help="where each request's pushes are kept, so a rerun resumes (default %(default)s)")
    parser.add_argument("--val-objects", default="", help="comma-separated ids (default: the val objects)")
    parser.add_argument("--train-objects", type=int, default=96,
                        help="train-split objects whose requests fine-tune the critic (default %(default)s)")
    parser.add_argument("--workers", type=int, default=2, help="spawn worker processes (default %(default)s)")
    parser.add_argument("--out", type=Path, default=Path("bench/results/critic_ranking.json"))
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args(argv)
    if args.train_objects < 1 or args.workers < 1:
        parser.error("--train-objects and --workers must be at least 1")
    summary = run(args)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=1) + "\n")
    for name, f in summary["orders"].items():
        print(f"{name:13s} first {summary['top']}: {f['top_pass']:.0%} pass, {f['top_error_cm']:.2f} cm from the target; "
              f"first pose {f['first_pass']:.0%}, {f['first_error_cm']:.2f} cm"
              + (f"; spearman {f['spearman']:.2f}" if "spearman" in f else ""))
    for point in summary["learning_curve"]:
        print(f"fine-tuned on {point['train_requests']} requests of {point['train_objects']} train objects: "
              f"first {summary['top']} {point['top_error_cm']:.2f} cm from the target, spearman {point['spearman']:.2f}")
    if args.json:
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Does a faster prescreen push decide as the validator's does? Pass/fail agreement and the planned order.

    python bench/prescreen_speed.py --json                     # val objects, 3 directions, speeds 0.1,0.2
    python bench/prescreen_speed.py --speeds 0.1,0.2,0.3 --objects proc-box-010,rnd-002

The prescreen (`shared.planning.stages.prescreen`) pushes the first 24 feasible poses of a request with the
validator's floating hand and plans the poses that pushed well first, closest to the target first. Pushing
faster simulates fewer steps (0.20 m at 0.1 m/s is 480 steps of 1/240 s; at 0.2 m/s, 240; the settle is the same).
What matters is whether the decision stays: for each request of `--objects` x the protocol's three directions
(the planner's default, K = 200, in this process through the evaluation's `LocalSystem`), the prescreen jobs the
planner sends are recorded, then pushed again at each of `--speeds` (the validator's own speed among them, a
check that the replay is the planner's: it must agree 100%). Measured, each against the validator's speed:

- `agreement`: the share of prescreened poses whose pass/fail is the same (the validator's solver setting agrees
  with its reference in 96-97 of 100 pushes and the reference with itself, poses moved 0.1 mm, in about 98:
  docs/architecture.md §Simulation);
- `first_same`: the share of requests whose first planned pose (the best passing one) is the same;
- `top_overlap`: the mean share of the first `max_plans` planned poses (one round of plans) that are the same set;
- `cpu_ms_per_push`: the CPU time of a replayed push.

`noise_floor`: the same figures for the validator's own speed with every pose moved 0.1 mm sideways (along D's y,
across the push): how much of a decision physics itself changes for a move no robot could tell. A faster speed
that changes no more than that loses nothing the prescreen knew.

`critic_order`: the same figures for no prescreen at all, read from the planner's own pushes (no replay): the
order the prescreen was handed (the critic's, which the planner follows without a prescreen) against the order
it planned in. `first_same` is then whether the critic's first pose is the prescreen's, `top_overlap` the share of
the critic's first `max_plans` among the prescreen's, and `agreement` the share of those first `max_plans` that
passed (what a planner without the prescreen would roll out). `--speeds none` measures only this.

The requests are planned but not executed (the robot is never asked to move). Val objects: settings are chosen on
val. The JSON is written to `--out`.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.contracts.messages import ObjectRef, PhysicsSettings, PushRequest, ValidationJob


class Planned(Exception):
    """Raised instead of executing: the bench stops every request once its plan is chosen."""


@dataclass
class Recorder:
    """The pipeline's `validate`: runs each job here, keeping the floating-hand (prescreen) jobs and results."""

    jobs: list[tuple[ValidationJob, Any]] = field(default_factory=list)

    def __call__(self, job: ValidationJob):  # type: ignore[no-untyped-def]
        from evaluation.local_system import validate_here

        future = validate_here(job)
        if not job.with_arm and future.exception() is None:
            self.jobs.append((job, future.result()))
        return future


def judged(result: Any) -> tuple[np.ndarray, np.ndarray]:
    """Per push of a result: whether it succeeded and how far from the target it left the object."""
    return result.success.to_numpy().astype(bool), result.position_error_m.to_numpy().astype(np.float64)


def planned_order(success: np.ndarray, error: np.ndarray) -> np.ndarray:
    """The prescreen's order of the poses it pushed: those that passed, closest to the target first (stable)."""
    passed = np.flatnonzero(success)
    return passed[np.argsort(error[passed], kind="stable")]


NOISE_NUDGE_M = 1e-4  # the noise floor's sideways move of every pose


def replayed(jobs: list[ValidationJob], speed: float, nudge_m: float = 0.0) -> tuple[np.ndarray, np.ndarray, float, int]:
    """The request's prescreen jobs pushed again at `speed`, every pose moved `nudge_m` along D's y: success, error,
    CPU seconds and pushes."""
    from shared.validation.jobs import validate
    from shared.world.sim.params import PhysicsParams

    nominal = PhysicsParams()
    physics = PhysicsSettings(solver_iterations=nominal.solver_iterations, time_step_s=nominal.time_step_s,
                              push_speed_mps=speed)
    started = time.process_time()
    parts = [judged(validate(replace_settings(nudged(job, nudge_m), physics))) for job in jobs]
    cpu = time.process_time() - started
    success = np.concatenate([p[0] for p in parts])
    return success, np.concatenate([p[1] for p in parts]), cpu, int(success.size)


def replace_settings(job: ValidationJob, physics: PhysicsSettings) -> ValidationJob:
    return job.model_copy(update={"settings": physics})


def nudged(job: ValidationJob, nudge_m: float) -> ValidationJob:
    """`job` with every hand pose moved `nudge_m` along D's y (a 25-d pose starts with the base's position)."""
    if nudge_m == 0.0:
        return job
    from shared.contracts.messages import NDArray

    poses = job.poses.to_numpy().astype(np.float64).copy()
    poses[:, 1] += nudge_m
    return job.model_copy(update={"poses": NDArray.from_numpy(poses.astype(job.poses.to_numpy().dtype))})


def compare(reference: tuple[np.ndarray, np.ndarray], other: tuple[np.ndarray, np.ndarray], top: int) -> dict[str, Any]:
    """How `other`'s prescreen decision of one request matches `reference`'s."""
    return compare_orders(planned_order(*reference), planned_order(*other), top) | {
        "agree": int(np.sum(reference[0] == other[0])), "pushes": int(reference[0].size),
        "passed_reference": int(reference[0].sum()), "passed": int(other[0].sum())}


def critic_compare(reference: tuple[np.ndarray, np.ndarray], top: int) -> dict[str, Any]:
    """How the order the prescreen was handed (the critic's: pushes 0, 1, ...) matches the order it planned in."""
    success = reference[0]
    critic = np.arange(success.size)
    return compare_orders(planned_order(*reference), critic, top) | {
        "agree": int(success[:top].sum()), "pushes": int(min(top, success.size)),
        "passed_reference": int(success.sum()), "passed": int(success[:top].sum())}


def compare_orders(order_ref: np.ndarray, order_other: np.ndarray, top: int) -> dict[str, Any]:
    """Whether two orders of poses start with the same pose, and the overlap of their first `top`."""
    first_same = (len(order_ref) == 0 and len(order_other) == 0) or (
        len(order_ref) > 0 and len(order_other) > 0 and order_ref[0] == order_other[0])
    top_ref, top_other = set(order_ref[:top].tolist()), set(order_other[:top].tolist())
    overlap = 1.0 if not top_ref and not top_other else len(top_ref & top_other) / max(len(top_ref), len(top_other))
    return {"first_same": bool(first_same), "top_overlap": overlap}


def main(argv: list[str] | None = None) -> int:
    from evaluation.methods import VAL_OBJECTS

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", default=",".join(VAL_OBJECTS), help="comma-separated ids (default: the val objects)")
    parser.add_argument("--speeds", default="0.1,0.2",
                        help="push speeds to replay at, m/s, or 'none' for the critic's order only (default %(default)s)")
    parser.add_argument("--out", default="bench/results/prescreen_speed.json", help="the JSON (default %(default)s)")
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args(argv)
    try:
        speeds = [] if args.speeds == "none" else [float(s) for s in args.speeds.split(",") if s]
    except ValueError:
        parser.error(f"--speeds takes comma-separated numbers (m/s) or 'none', got {args.speeds!r}")
    if speeds and (min(speeds) <= 0 or max(speeds) > 2.0):
        parser.error("--speeds must be in (0, 2] m/s")
    objects = [o for o in args.objects.split(",") if o]
    return run(objects, speeds, Path(args.out), args.json)


def run(objects: list[str], speeds: list[float], out: Path, print_json: bool) -> int:
    import torch
    from tqdm import tqdm

    from evaluation.local_system import LocalSystem, sampler_source
    from evaluation.push_protocol import DIRECTIONS_DEG
    from evaluation.report import code_version, machine
    from shared.planning.pipeline import PushPipeline, PushServices
    from shared.planning.stages import PipelineSettings
    from shared.world.sim.params import PhysicsParams

    torch.set_num_threads(1)
    nominal = PhysicsParams().push_speed_mps
    settings = PipelineSettings()
    system = LocalSystem(settings)
    # each replay: (speed, sideways move); the noise floor last, unless only the critic's order is asked for
    replays = [(s, 0.0) for s in speeds] + ([(nominal, NOISE_NUDGE_M)] if speeds else [])
    per_speed: dict[tuple[float, float], list[dict[str, Any]]] = {r: [] for r in replays}
    cpu: dict[tuple[float, float], list[float]] = {r: [] for r in replays}
    critic_rows: list[dict[str, Any]] = []
    requests = [(o, d) for o in objects for d in DIRECTIONS_DEG]

    def refuse(*_args: object) -> Any:
        raise Planned

    try:
        for object_id, direction in tqdm(requests, desc="prescreen", unit="request"):
            recorder = Recorder()
            pipeline = PushPipeline(PushServices(sample=sampler_source(system.sampler), validate=recorder,
                                                 execute=refuse), settings)
            try:
                pipeline.run(PushRequest(object=ObjectRef(library_id=object_id), direction_deg=direction))
            except Exception:  # Planned, or no plan at all: what was prescreened is what counts
                pass
            finally:
                pipeline.close()
            jobs = [job for job, _ in recorder.jobs]
            if not jobs:
                continue
            planner = (np.concatenate([judged(r)[0] for _, r in recorder.jobs]),
                       np.concatenate([judged(r)[1] for _, r in recorder.jobs]))
            critic_rows.append({"object": object_id, "direction_deg": direction,
                                **critic_compare(planner, settings.max_plans)})
            for speed, nudge in replays:
                success, error, seconds, pushes = replayed(jobs, speed, nudge)
                cpu[speed, nudge].append(seconds / pushes)
                row = compare(planner, (success, error), settings.max_plans)
                per_speed[speed, nudge].append({"object": object_id, "direction_deg": direction, **row})
    finally:
        system.close()
    summary: dict[str, Any] = {"command": "python bench/prescreen_speed.py " + " ".join(sys.argv[1:]), "date": time.strftime("%Y-%m-%d"),
                               "code": code_version(), "machine": machine(), "reference_speed_mps": nominal,
                               "objects": objects, "requests": len(requests), "speeds": {}}
    named = [(f"{speed:g}" if nudge == 0.0 else "noise_floor", rows, cpu[speed, nudge])
             for (speed, nudge), rows in per_speed.items()] + [("critic_order", critic_rows, [])]
    for name, rows, per_push in named:
        pushes = sum(r["pushes"] for r in rows)
        summary["speeds"][name] = {
            "requests_prescreened": len(rows), "pushes": pushes,
            "agreement": round(sum(r["agree"] for r in rows) / max(pushes, 1), 4),
            "first_same": round(float(np.mean([r["first_same"] for r in rows])) if rows else 0.0, 4),
            "top_overlap": round(float(np.mean([r["top_overlap"] for r in rows])) if rows else 0.0, 4),
            "passed_share": round(sum(r["passed"] for r in rows) / max(pushes, 1), 4),
            "cpu_ms_per_push": round(1000 * float(np.mean(per_push)), 1) if per_push else None,
            "per_request": rows}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(summary, indent=1) + "\n")
    for speed, figures in summary["speeds"].items():
        print(f"{speed}{'' if speed in ('noise_floor', 'critic_order') else ' m/s'}: agreement {figures['agreement']:.1%} over {figures['pushes']} pushes, first pose the same "
              f"in {figures['first_same']:.0%}, top {settings.max_plans} overlap {figures['top_overlap']:.0%}, "
              f"{figures['cpu_ms_per_push']} ms CPU per push")
    if print_json:
        print(json.dumps({k: v for k, v in summary.items() if k != "speeds"}
                         | {"speeds": {s: {k: v for k, v in f.items() if k != "per_request"}
                                       for s, f in summary["speeds"].items()}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

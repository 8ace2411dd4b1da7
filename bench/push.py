"""End-to-end push requests: latency by stage and success over a fixed set of objects and directions.

    python bench/push.py --json      # last line: one JSON object

The system runs as `gd2p up` brings it up (`deploy.launcher`: an embedded router and one process
per service, one validator per core unless `--validators`); each request goes through the push
client exactly as `gd2p push` sends it, one at a time (the next once the previous storyboard is
rendered). Start-up is not timed. K = 200 candidate poses from the diffusion sampler
(method "gd2p"; `--sampler ddim --no-prescreen` for the fast path: the success critic's order, no prescreen) when an
Allegro checkpoint is at the default
path, else the fixed spatula pose (method "fixed", one candidate) — the JSON says which. Stages
(from the response's timings): sampling, ik (batched IK + collision and push-line screen),
prescreen (floating-hand pushes of the best-aligned feasible poses), planning (RRTConnect +
Cartesian segments; the validators roll finished plans out meanwhile), rollouts (the wait for the
last arm rollouts after planning), execution (the simulated robot bridge, at full physics speed);
"total" is the client's wall time per request, `to_plan_s` everything before execution.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from client.push_client import PushFailed, push
from deploy.launcher import Launcher, free_loopback_endpoint
from shared.bus import BusConfig
from shared.contracts.messages import ObjectRef, PlannerOptions, PushRequest

OBJECTS = ("proc-box-013", "proc-box-000", "proc-cylinder-000")  # test split
DIRECTIONS_DEG = (90.0, -90.0)  # sideways both ways from the default spot 0.55 m in front of the robot
STAGES = ("sampling", "ik", "prescreen", "planning", "rollouts", "execution")


def start_system(record_dir: str, validators: int | None) -> tuple[Launcher, BusConfig]:
    """The system as `gd2p up` brings it up (router + one process per service); (launcher, client config)."""
    launcher = Launcher(validators=validators, listen=free_loopback_endpoint(), record_dir=record_dir)
    launcher.start()
    try:
        launcher.wait_ready(120.0)
    except BaseException:
        launcher.stop()
        raise
    return launcher, BusConfig(mode="client", connect=[launcher.endpoint], connect_timeout_ms=5000)


def wait_for_storyboard(recording_path: str | None, timeout_s: float = 60.0) -> None:
    """Until the planner has rendered the request's storyboard (after answering, on its own thread).

    Each request is then timed alone: back to back, the previous storyboard's rendering shares the
    planner's CPU and adds about 0.5 s to the next request's IK and planning stages.
    """
    if recording_path is None:
        return
    png = Path(recording_path).with_suffix(".png")
    deadline = time.monotonic() + timeout_s
    while not png.exists() and time.monotonic() < deadline:
        time.sleep(0.1)


def percentile(values: list[float], q: float) -> float:
    return round(float(np.percentile(values, q)), 3) if values else float("nan")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    parser.add_argument("--k", type=int, default=200)
    parser.add_argument("--method", choices=("auto", "gd2p", "fixed"), default="auto")
    parser.add_argument("--sampler", choices=("ddpm", "ddim"), default="ddpm",
                        help="diffusion sampler of method gd2p (DDIM-10: the fast path)")
    parser.add_argument("--no-critic", dest="critic", action="store_false",
                        help="PlannerOptions.critic off: L_dir's order instead of the success critic's (the default)")
    parser.add_argument("--no-prescreen", dest="prescreen", action="store_false",
                        help="PlannerOptions.prescreen off: no floating-hand pushes before planning (with DDIM: the fast path)")
    parser.add_argument("--record-dir", default="/tmp/gd2p-bench-push")
    parser.add_argument("--validators", type=int, default=None,
                        help="validator processes (default: one per core, as `gd2p up`)")
    args = parser.parse_args(argv)
    from shared.sampling.checkpoint import default_checkpoint_path

    method = args.method
    if method == "auto":
        method = "gd2p" if default_checkpoint_path("allegro").is_file() else "fixed"
    launcher, cfg = start_system(args.record_dir, args.validators)
    rows = []
    try:
        for object_id in OBJECTS:
            for direction in DIRECTIONS_DEG:
                options = PlannerOptions(k=args.k, method=method, sampler=args.sampler, critic=args.critic,
                                         prescreen=args.prescreen)
                request = PushRequest(object=ObjectRef(library_id=object_id), direction_deg=direction, options=options)
                started = time.perf_counter()
                try:
                    response = push(request, cfg, timeout_s=300.0)
                    row = {"object": object_id, "direction_deg": direction, "success": response.success,
                           "position_error_m": round(response.result.position_error_m, 4),
                           "rotation_deg": round(response.result.rotation_deg, 1),
                           "stages_s": {k: round(v, 3) for k, v in response.timings_s.items()}}
                except PushFailed as exc:
                    row = {"object": object_id, "direction_deg": direction, "success": False, "error": exc.code,
                           "message": exc.message[:200]}
                row["total_s"] = round(time.perf_counter() - started, 3)
                rows.append(row)
                if "stages_s" in row:
                    wait_for_storyboard(response.recording_path)
                if not args.json:
                    print(json.dumps(row))
    finally:
        launcher.stop()
    served = [r for r in rows if "stages_s" in r]
    totals = [r["total_s"] for r in served]
    to_plan = [sum(r["stages_s"].get(s, 0.0) for s in STAGES if s != "execution") for r in served]
    from evaluation.report import code_version, machine

    summary = {
        "machine": machine(), "date": time.strftime("%Y-%m-%d"), "code": code_version(),
        "method": method, "sampler": args.sampler if method == "gd2p" else None, "critic": args.critic, "prescreen": args.prescreen, "validators": args.validators or os.cpu_count(), "k": args.k if method == "gd2p" else 1, "requests": len(rows),
        "success": sum(r["success"] for r in rows), "success_rate": round(sum(r["success"] for r in rows) / len(rows), 3),
        "infeasible": sum(r.get("error") == "infeasible" for r in rows),
        "latency_s": {"p50": percentile(totals, 50), "p95": percentile(totals, 95), "target_p50": 3.0},
        # Until the plan is chosen (every stage but execution, which takes the robot's own time on hardware).
        "to_plan_s": {"p50": percentile(to_plan, 50), "p95": percentile(to_plan, 95), "target_p50": 1.5,
                      "target_p95": 3.0},
        "stages_s": {s: {"p50": percentile([r["stages_s"].get(s, 0.0) for r in served], 50),
                         "p95": percentile([r["stages_s"].get(s, 0.0) for r in served], 95)} for s in STAGES},
        "median_total_in_planner_s": round(statistics.median([r["stages_s"]["total"] for r in served]), 3) if served else None,
        "rows": rows,
    }
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""End-to-end push requests: latency by stage and success over a fixed set of objects and directions.

    python bench/push.py --json      # last line: one JSON object

An embedded router and the workers the request needs (planner, validator, robot bridge, and the
sampler when a checkpoint exists) run in this process as threads; each request goes through the
push client exactly as `gd2p push` sends it. K = 200 candidate poses from the diffusion sampler
(method "gd2p") when an Allegro checkpoint is at the default path, else the fixed spatula pose
(method "fixed", one candidate) — the JSON says which. Stages (from the response's timings):
sampling, ik (batched IK + collision screen), prescreen (floating-hand pushes of the best-aligned
feasible poses), planning (RRTConnect + Cartesian segments),
rollouts (arm rollouts of the candidate plans on the validator), execution (the simulated robot
bridge, at full physics speed); "total" is the client's wall time per request.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.bus import BusConfig, live_workers, open_session, run_worker  # noqa: E402
from shared.messages import ObjectRef, PushRequest  # noqa: E402
from shared.push_client import PushFailed, push  # noqa: E402

OBJECTS = ("proc-box-013", "proc-box-000", "proc-cylinder-000")  # test split
DIRECTIONS_DEG = (90.0, -90.0)  # sideways both ways from the default spot 0.55 m in front of the robot
STAGES = ("sampling", "ik", "prescreen", "planning", "rollouts", "execution")


def start_system(endpoint: str, record_dir: str, with_sampler: bool, stop: threading.Event,
                 threads: list[threading.Thread]) -> tuple[BusConfig, zenoh.Session]:
    """Open an embedded router and start the workers (threads in `threads`); (client config, router)."""

    from services.planner import service as planner
    from services.robot_bridge import service as bridge
    from services.sampler import service as sampler
    from services.validator import service as validator

    router = zenoh.Config()
    router.insert_json5("mode", json.dumps("router"))
    router.insert_json5("listen/endpoints", json.dumps([endpoint]))
    router.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(router)
    cfg = BusConfig(mode="client", connect=[endpoint], connect_timeout_ms=5000)
    targets = [(bridge.run, (cfg, "bench-bridge", stop), {}),
               (run_worker, (validator.SERVICE, validator.handlers(), cfg, "bench-validator"), {"stop": stop}),
               (planner.run, (cfg, "bench-planner", stop, record_dir), {})]
    if with_sampler:
        targets.append((run_worker, (sampler.SERVICE, sampler.handlers(), cfg, "bench-sampler"), {"stop": stop}))
    for target, args, kwargs in targets:
        thread = threading.Thread(target=target, args=args, kwargs=kwargs, daemon=True)
        thread.start()
        threads.append(thread)
    wanted = {"planner", "validator", "robot_bridge"} | ({"sampler"} if with_sampler else set())
    with open_session(cfg) as client:
        deadline = time.monotonic() + 60.0
        while not all(live_workers(client).get(s) for s in wanted):
            if time.monotonic() > deadline:
                raise RuntimeError("the workers did not register within 60 s")
            time.sleep(0.2)
    return cfg, session


def percentile(values: list[float], q: float) -> float:
    return round(float(np.percentile(values, q)), 3) if values else float("nan")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    parser.add_argument("--k", type=int, default=200)
    parser.add_argument("--method", choices=("auto", "gd2p", "fixed"), default="auto")
    parser.add_argument("--record-dir", default="/tmp/gd2p-bench-push")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    from services.sampler.checkpoint import default_checkpoint_path
    from tests.conftest import free_port

    method = args.method
    if method == "auto":
        method = "gd2p" if default_checkpoint_path("allegro").is_file() else "fixed"
    stop = threading.Event()
    threads: list[threading.Thread] = []
    cfg, router = start_system(f"tcp/127.0.0.1:{free_port()}", args.record_dir, method == "gd2p", stop, threads)
    rows = []
    try:
        for object_id in OBJECTS:
            for direction in DIRECTIONS_DEG:
                request = PushRequest(object=ObjectRef(library_id=object_id), direction_deg=direction, k=args.k,
                                      method=method)
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
                if not args.json:
                    print(json.dumps(row))
    finally:
        stop.set()
        for thread in threads:
            thread.join(timeout=15.0)
        router.close()
    served = [r for r in rows if "stages_s" in r]
    totals = [r["total_s"] for r in served]
    summary = {
        "method": method, "k": args.k if method == "gd2p" else 1, "requests": len(rows),
        "success": sum(r["success"] for r in rows), "success_rate": round(sum(r["success"] for r in rows) / len(rows), 3),
        "infeasible": sum(r.get("error") == "infeasible" for r in rows),
        "latency_s": {"p50": percentile(totals, 50), "p95": percentile(totals, 95), "target_p50": 3.0},
        "stages_s": {s: {"p50": percentile([r["stages_s"].get(s, 0.0) for r in served], 50),
                         "p95": percentile([r["stages_s"].get(s, 0.0) for r in served], 95)} for s in STAGES},
        "median_total_in_planner_s": round(statistics.median([r["stages_s"]["total"] for r in served]), 3) if served else None,
        "rows": rows,
    }
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""What a trial costs in each execution world: the same trials in `real` (PyBullet) and `mujoco`, in one run.

    python bench/world_cost.py --json          # last line: one JSON object (also bench/results/world_cost.json)

Each trial is the evaluation's own (`evaluation.push_protocol.run_episode`: plan with the default method through
3 simulated cameras, execute, judge), in this process, one at a time, the worlds alternating so that a machine
growing busier weighs on both alike. The same episodes (object, direction, trial: the same placements, captures
and drawn quantities) run in `real` with the image tracker, in `mujoco` with the image tracker, and in `real` with
the truth-plus-noise tracker (what tracking from images costs). Reported per configuration: the median and total
seconds per trial and the execution stage's median; `mujoco_over_real` is the ratio of medians (the budget: at
most 1.5). Run it on an idle machine.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("MUJOCO_GL", "egl")

from evaluation import push_protocol as protocol
from shared.execution.robots import TrackingMode
from shared.world.sim.world import WorldLevel

OBJECTS = ("proc-box-000", "proc-cylinder-001", "pb-mug")  # development split: a box, a round object, a handle
DIRECTIONS_DEG = (60.0, 180.0)
CONFIGS: tuple[tuple[WorldLevel, TrackingMode], ...] = (("real", "image"), ("mujoco", "image"), ("real", "truth"))
METHOD = "gd2p-closed-critic-p24"  # the planner's default


def run(trials: int) -> dict[str, Any]:
    protocol._init_worker(str(Path("/tmp/gd2p-bench-grasp")))
    times: dict[str, list[float]] = {f"{w}/{t}": [] for w, t in CONFIGS}
    execution: dict[str, list[float]] = {key: [] for key in times}
    outcomes: dict[str, list[str]] = {key: [] for key in times}
    for object_id in OBJECTS:
        for direction in DIRECTIONS_DEG:
            for trial in range(trials):
                for world, tracking in CONFIGS:
                    episode = protocol.Episode(METHOD, "allegro", object_id, direction, trial, world, 3, tracking)
                    started = time.perf_counter()
                    record = protocol.run_episode(episode)
                    key = f"{world}/{tracking}"
                    times[key].append(time.perf_counter() - started)
                    execution[key].append(float(record.get("timings_s", {}).get("execution", float("nan"))))
                    outcomes[key].append(record["outcome"])
                    print(f"{key:14s} {object_id:20s} {direction:5.0f} {trial} {times[key][-1]:6.1f} s "
                          f"{record['outcome']}", file=sys.stderr, flush=True)
    summary = {key: {"trials": len(v), "median_s": round(statistics.median(v), 2), "total_s": round(sum(v), 1),
                     "execution_median_s": round(statistics.median(execution[key]), 2),
                     "successes": outcomes[key].count("success")} for key, v in times.items()}
    return {"configs": summary,
            "mujoco_over_real": round(summary["mujoco/image"]["median_s"] / summary["real/image"]["median_s"], 3),
            "image_over_truth": round(summary["real/image"]["median_s"] / summary["real/truth"]["median_s"], 3)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=1, help="trials per object and direction (default %(default)s)")
    parser.add_argument("--json", action="store_true", help="print one JSON object last and write bench/results/world_cost.json")
    args = parser.parse_args()
    result = run(args.trials)
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).resolve().parents[1]).stdout.strip()
    out = {"bench": "world_cost", "command": " ".join(["python", *sys.argv]), "commit": commit,
           "cpus": os.cpu_count(), "method": METHOD, "objects": OBJECTS, "directions_deg": DIRECTIONS_DEG,
           "trials": args.trials, **result}
    if args.json:
        path = Path(__file__).resolve().parent / "results" / "world_cost.json"
        path.write_text(json.dumps(out, indent=2) + "\n")
        print(json.dumps(out))
    else:
        print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

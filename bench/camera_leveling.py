"""Does levelling each camera to the table keep miscalibrated cameras' table out of the object?

    python bench/camera_leveling.py            # val objects; writes bench/results/camera_leveling.json
    python bench/camera_leveling.py --quick    # 4 objects x 1 draw, printed only

The captures the closed-loop evaluation makes (evaluation/push_protocol.py: the object re-placed with noise in front
of the robot, 3 cameras at the default size with D435-class noise, each camera off its calibration by its drawn
`real` world's error: up to 3 mm and 0.3 degrees per axis), of val objects, each captured twice from the same
draw: with every frame levelled to the table (`shared.world.perception.depth.level_to_table`, the default) and with
the frames as calibrated. Each cloud goes through what the planner does with a request's cloud (`cloud_for_request`,
`object_from_cloud`). Per capture: refused, or the reconstruction's horizontal reach from its centre of mass against
the true object's (a patch of table clustered with the object shows as reach the object does not have), the
centre-of-mass error in the table plane and the table's height spread under the object's neighbourhood.

Objects: every `--stride`-th val id (sorted), `--draws` world draws each (the protocol's seeds for trial 0..draws-1
of direction 60).
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from evaluation.push_protocol import Episode, episodes, execution_world, placement  # noqa: E402
from shared.world.objects import list_object_ids, load_object  # noqa: E402
from shared.world.perception import PerceptionError, cloud_for_request  # noqa: E402
from shared.world.perception.object_model import object_from_cloud  # noqa: E402
from shared.world.sim.camera import capture_object  # noqa: E402

OUT = ROOT / "bench" / "results" / "camera_leveling.json"
EXCESS_M = 0.02  # reach beyond the true object's by more than this: table clustered with the object
METHOD = "gd2p-closed-critic-p24"  # any method: only the episodes' seeds are used


@dataclass(frozen=True)
class Outcome:
    refused: str | None
    excess_reach_m: float = float("nan")
    com_error_m: float = float("nan")


def reach(vertices: np.ndarray, centre: np.ndarray) -> float:
    return float(np.max(np.linalg.norm(vertices[:, :2] - centre[:2], axis=1)))


def measure(episode: Episode, level: bool, cache: Path) -> Outcome:
    obj = load_object(episode.object_id)
    world = execution_world(episode)
    T_true = world.pose_error.true_pose(placement(episode))
    capture = capture_object(obj, T_true, n_cameras=episode.cameras, seed=episode.world_seed,
                             camera_errors=world.camera_errors, level=level)
    truth = obj.mesh.copy()
    truth.apply_transform(T_true)
    try:
        seen = object_from_cloud(cloud_for_request(capture.cloud), cache_dir=cache)
    except PerceptionError as exc:
        return Outcome(str(exc)[:160])
    mesh = seen.model.mesh.copy()
    mesh.apply_transform(seen.T_world_O)
    com_seen, com_true = np.asarray(mesh.center_mass), np.asarray(truth.center_mass)
    excess = reach(np.asarray(mesh.vertices), com_seen) - reach(np.asarray(truth.vertices), com_true)
    return Outcome(None, excess, float(np.linalg.norm(com_seen[:2] - com_true[:2])))


def summarise(outcomes: list[Outcome]) -> dict[str, float | int]:
    ok = [o for o in outcomes if o.refused is None]
    excess = [o.excess_reach_m for o in ok]
    return {
        "captures": len(outcomes),
        "refused": len(outcomes) - len(ok),
        "table_in_object": sum(e > EXCESS_M for e in excess),
        "excess_reach_mm_p50": round(1000 * statistics.median(excess), 1) if excess else float("nan"),
        "excess_reach_mm_max": round(1000 * max(excess), 1) if excess else float("nan"),
        "com_error_mm_p50": round(1000 * statistics.median(o.com_error_m for o in ok), 1) if ok else float("nan"),
        "com_error_mm_p95": round(1000 * float(np.percentile([o.com_error_m for o in ok], 95)), 1) if ok else float("nan"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--stride", type=int, default=5, help="every STRIDE-th val object (default 5)")
    parser.add_argument("--draws", type=int, default=3, help="world draws per object (default 3)")
    parser.add_argument("--quick", action="store_true", help="4 objects x 1 draw, not written")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    objects = list_object_ids("val")[:: args.stride]
    draws = args.draws
    if args.quick:
        objects, draws = objects[:4], 1
    trials = episodes([METHOD], "allegro", objects, [60.0], draws, world="real", cameras=3, split="val")
    started = time.perf_counter()
    results: dict[str, list[Outcome]] = {"levelled": [], "as calibrated": []}
    failures: list[dict[str, str | float]] = []
    with tempfile.TemporaryDirectory() as cache:
        for k, episode in enumerate(trials):
            for label, level in (("levelled", True), ("as calibrated", False)):
                outcome = measure(episode, level, Path(cache))
                results[label].append(outcome)
                if outcome.refused or outcome.excess_reach_m > EXCESS_M:
                    failures.append({"object": episode.object_id, "trial": episode.trial, "capture": label,
                                     "refused": outcome.refused or "", "excess_reach_mm": round(1000 * outcome.excess_reach_m, 1)})
            print(f"\r{k + 1}/{len(trials)} captures", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    report = {
        "command": " ".join(["python", *sys.argv]),
        "commit": subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout.strip(),
        "objects": len(objects), "draws": draws, "seconds": round(time.perf_counter() - started, 1),
        "excess_threshold_mm": 1000 * EXCESS_M,
        **{label: summarise(outcomes) for label, outcomes in results.items()},
        "failures": failures,
    }
    print(json.dumps(report, indent=1))
    if not args.quick:
        args.out.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()

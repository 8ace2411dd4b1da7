"""What a push's decision depended on, written into its recording, and how two decisions compare.

A push recording (services/planner/recording.py) carries the request (with its point cloud, when the
object came as a capture) as a bus message, and this module's metadata record `gd2p.decision`:
- `commit`: the code that decided ($GD2P_COMMIT, else `git rev-parse HEAD`, "-dirty" when tracked files
  differ from it, else "unknown");
- `models`: JSON {"diffusion", "critic", "nn_index": "sha256:<hex>" | "none" | "missing: <path>"} as a
  sampler on the planner's host resolves them (shared/sampling/models.py);
- `seeds`: JSON {"request": the request's seed (sampling, rollout worlds, random choices), "motion_planner":
  the OMPL seed of every RRTConnect call, "ik": the IK solver's start configurations};
- `settings`: the pipeline's settings (`PipelineSettings`, repr), `versions` of the numeric libraries, the
  request id, arm, hand and method.
`gd2p replay FILE.mcap --resim` (evaluation/resim.py) plans the request again in process and compares the
chosen plans bit for bit (`compare_plans`).
"""
from __future__ import annotations

import functools
import json
import os
import platform
import subprocess
from dataclasses import dataclass
from importlib import metadata as importlib_metadata
from pathlib import Path

import numpy as np

from shared.contracts.messages import Plan, PushRequest

METADATA_NAME = "gd2p.decision"
VERSION = "1"
COMMIT_ENV = "GD2P_COMMIT"  # where there is no git checkout (a container image)
IK_SEED = 0  # ArmIK's default seed, which the pipeline uses (shared/planning/ik.py)
LIBRARIES = ("numpy", "torch", "pybullet", "ompl", "pytorch_kinematics", "scipy")
REQUIRED = ("commit", "models", "seeds", "settings")


@functools.lru_cache(maxsize=1)
def current_commit() -> str:
    """$GD2P_COMMIT, else this checkout's `git rev-parse HEAD` ("-dirty" with tracked changes), else "unknown"."""
    if os.environ.get(COMMIT_ENV):
        return os.environ[COMMIT_ENV]
    here = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=10,
                                check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here, capture_output=True,
                               text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (f"{commit}-dirty" if dirty else commit) or "unknown"


@functools.lru_cache(maxsize=1)
def library_versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for name in LIBRARIES:
        try:
            versions[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            continue
    return versions


def seeds(request: PushRequest) -> dict[str, int]:
    from shared.planning.motion import MotionSettings

    return {"request": int(request.seed), "motion_planner": int(MotionSettings().seed), "ik": IK_SEED}


def decision_metadata(request: PushRequest, settings: object, models: dict[str, str]) -> dict[str, str]:
    """The `gd2p.decision` metadata record of a push of `request` planned with `settings` and `models`."""
    return {"version": VERSION, "commit": current_commit(), "request_id": request.id, "arm": request.arm,
            "hand": request.hand, "method": request.method, "models": json.dumps(models, sort_keys=True),
            "seeds": json.dumps(seeds(request), sort_keys=True), "settings": repr(settings),
            "versions": json.dumps(library_versions(), sort_keys=True),
            "capture": (f"point cloud of {request.object.point_cloud.shape[0]} points (in the request)"
                        if request.object.point_cloud is not None else f"library object {request.object.library_id}")}


@dataclass(frozen=True)
class Mismatch:
    """One way a recorded decision's context differs from this process's: `what` and both values."""

    what: str
    recorded: str
    here: str

    def __str__(self) -> str:
        return f"{self.what}: recorded {self.recorded}, here {self.here}"


def context_mismatches(recorded: dict[str, str], request: PushRequest, settings: object,
                       models: dict[str, str]) -> list[Mismatch]:
    """Where the recording's decision context (`gd2p.decision`) differs from planning it again here."""
    here = decision_metadata(request, settings, models)
    found = []
    for key in ("commit", "settings", "seeds"):
        if key in recorded and recorded[key] != here[key]:
            found.append(Mismatch(key, recorded[key], here[key]))
    if "models" in recorded:
        then, now = json.loads(recorded["models"]), models
        found += [Mismatch(f"model {name}", str(then.get(name)), str(now.get(name)))
                  for name in sorted(set(then) | set(now)) if then.get(name) != now.get(name)]
    if "versions" in recorded:
        then, now = json.loads(recorded["versions"]), library_versions()
        found += [Mismatch(f"library {name}", str(then.get(name)), str(now.get(name)))
                  for name in sorted(set(then) | set(now)) if then.get(name) != now.get(name)]
    return found


def compare_plans(recorded: Plan, replanned: Plan) -> list[str]:
    """How `replanned` differs from `recorded` ([] when identical bit for bit: names, segments, every waypoint
    and time as float64 bytes), with where and by how much."""
    differences = []
    if (recorded.arm, recorded.hand) != (replanned.arm, replanned.hand):
        differences.append(f"robot: {recorded.arm}+{recorded.hand} vs {replanned.arm}+{replanned.hand}")
    if list(recorded.joint_names) != list(replanned.joint_names):
        differences.append("joint names differ")
    if [s.model_dump() for s in recorded.segments] != [s.model_dump() for s in replanned.segments]:
        differences.append(f"segments: {_segments(recorded)} vs {_segments(replanned)}")
    for what, a, b in (("waypoints", recorded.positions.to_numpy(), replanned.positions.to_numpy()),
                       ("times", recorded.times_s.to_numpy(), replanned.times_s.to_numpy())):
        if a.shape != b.shape:
            differences.append(f"{what}: shape {a.shape} vs {b.shape}")
            continue
        if a.dtype == b.dtype and a.tobytes() == b.tobytes():
            continue
        gap = np.abs(a.astype(np.float64) - b.astype(np.float64))
        where = np.unravel_index(int(np.nanargmax(gap)), gap.shape)
        differing = int(np.count_nonzero(a != b))
        detail = f"{what}: {differing} of {a.size} values differ, at most {float(np.nanmax(gap)):.3g}"
        if what == "waypoints":
            detail += f" (waypoint {where[0]}, joint {recorded.joint_names[where[1]]})"
        else:
            detail += f" (waypoint {where[0]})"
        differences.append(detail)
    return differences


def _segments(plan: Plan) -> str:
    return ", ".join(f"{s.label}[{s.start}:{s.stop}]" for s in plan.segments)

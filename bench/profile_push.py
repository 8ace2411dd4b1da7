"""Where a push's time goes, per library call, of the planner's default.

    python bench/profile_push.py --json      # last line: one JSON object; also writes --out (markdown)

The pushes of bench/push.py (the same objects and directions, the planner's default options, K = 200) run in
this one process through the evaluation's in-process system (`evaluation.local_system.LocalSystem`: the sampler
service's handler, the validator's physics and the simulated robot, the same pipeline as the planner service),
under cProfile in every thread (the robot's execution runs in one of its own), after one untimed warm-up push.
Per library: the profile's own time (tottime) of every function, grouped by where its code lives (a package under
site-packages, a C extension such as pybullet's calls, or a layer of this project), so what each 100 ms buys is
visible down to the library call. Per stage the distributed system's figures are bench/push.py's: in process the
validators' work runs inside the calls that submit it, so the pipeline's stage clocks would misplace it. In
process everything runs on one core, so read the shares, not the seconds.
"""
from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.contracts.messages import ObjectRef, PushRequest

OBJECTS = ("proc-box-013", "proc-box-000", "proc-cylinder-000")  # bench/push.py's
DIRECTIONS_DEG = (90.0, -90.0)
BUILTIN_GROUPS = {"<built-in method pybullet": "pybullet (C)", "<built-in method torch": "torch (C)",
                  "<method '": "python builtins", "<built-in method": "python builtins"}


def where(filename: str, function: str) -> str:
    """The group a profiled function belongs to: its package, its project layer, or its C extension."""
    if filename == "~":
        if "_thread.lock" in function or "_thread.RLock" in function:
            return "waiting on another thread (not work)"
        for prefix, group in BUILTIN_GROUPS.items():
            if function.startswith(prefix):
                return group
        return "python builtins"
    path = Path(filename)
    if "site-packages" in path.parts:
        return path.parts[path.parts.index("site-packages") + 1].split(".")[0]
    parts = path.parts
    for top in ("shared", "services", "evaluation", "visualisation", "client"):
        if top in parts:
            i = parts.index(top)
            return "/".join(parts[i:i + 2]).removesuffix(".py")
    return "python stdlib"


def by_library(stats: pstats.Stats) -> dict[str, float]:
    groups: dict[str, float] = defaultdict(float)
    for (filename, _line, function), (_cc, _nc, tottime, _cumtime, _callers) in stats.stats.items():  # type: ignore[attr-defined]
        groups[where(filename, function)] += tottime
    return dict(sorted(groups.items(), key=lambda kv: -kv[1]))


def top_calls(stats: pstats.Stats, n: int) -> list[dict[str, Any]]:
    rows = sorted(stats.stats.items(), key=lambda kv: -kv[1][2])[:n]  # type: ignore[attr-defined]
    return [{"function": f"{Path(filename).name}:{line} {function}", "group": where(filename, function),
             "calls": int(nc), "own_s": round(tottime, 3), "cumulative_s": round(cumtime, 3)}
            for (filename, line, function), (_cc, nc, tottime, cumtime, _callers) in rows]


def markdown(summary: dict[str, Any]) -> str:
    total = summary["profiled_s"]
    intro = (f"`{summary['command']}`: {summary['pushes']} pushes of bench/push.py's set ({summary['successes']} "
             f"succeeded), the planner's default (K = 200), in one process (evaluation's LocalSystem) under cProfile "
             f"in {summary['threads_profiled']} threads, after a warm-up push; {summary['wall_s']} s wall; "
             f"{summary['machine']}. In process everything runs on one core (the distributed system overlaps the "
             "validators' physics with planning): read the shares. Per stage: bench/push.py.")
    lines = [f"# Where a push's time goes ({summary['date']}, {summary['code']})", "", intro, "",
             "## Per library (own time, every thread)", "", "| where | s | share |", "|---|---|---|"]
    lines += [f"| {g} | {v:.2f} | {100 * v / total:.0f}% |" for g, v in list(summary["by_library_s"].items())[:20]]
    lines += ["", "## The 25 functions with the most own time", "", "| function | where | calls | own s | cumulative s |",
              "|---|---|---|---|---|"]
    lines += [f"| `{r['function']}` | {r['group']} | {r['calls']} | {r['own_s']} | {r['cumulative_s']} |"
              for r in summary["top_functions"]]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    parser.add_argument("--out", default="bench/results/profile_push.md",
                        help="the markdown report, and beside it the JSON (default %(default)s)")
    args = parser.parse_args(argv)
    import torch

    from evaluation.local_system import LocalSystem
    from evaluation.report import code_version, machine

    torch.set_num_threads(1)
    system = LocalSystem()
    pipeline = system.pipeline("sampler")
    requests = [PushRequest(object=ObjectRef(library_id=o), direction_deg=d) for o in OBJECTS for d in DIRECTIONS_DEG]
    try:
        pipeline.run(requests[0])  # warm-up: models, scenes and caches load once
        profilers = [cProfile.Profile()]

        def profile_thread(*_args: object) -> None:  # the first event of every new thread: its own profiler
            profiler = cProfile.Profile()
            profilers.append(profiler)
            profiler.enable()

        successes = 0
        started = time.perf_counter()
        threading.setprofile(profile_thread)
        profilers[0].enable()
        for request in requests:
            successes += pipeline.run(request).response.success
        profilers[0].disable()
        threading.setprofile(None)  # type: ignore[arg-type]
        wall = time.perf_counter() - started
    finally:
        system.close()
    for profiler in profilers[1:]:
        profiler.disable()
    stats = pstats.Stats(profilers[0])
    for profiler in profilers[1:]:
        stats.add(profiler)
    profiled = sum(v[2] for v in stats.stats.values())  # type: ignore[attr-defined]
    summary = {"command": "python bench/profile_push.py --json", "date": time.strftime("%Y-%m-%d"),
               "code": code_version(), "machine": machine(), "pushes": len(requests), "successes": successes,
               "wall_s": round(wall, 2), "profiled_s": round(profiled, 2),
               "threads_profiled": len(profilers),
               "by_library_s": {g: round(v, 3) for g, v in by_library(stats).items()},
               "top_functions": top_calls(stats, 25)}
    Path(args.out).write_text(markdown(summary))
    Path(args.out).with_suffix(".json").write_text(json.dumps(summary, indent=1) + "\n")
    print(f"{len(requests)} pushes ({successes} succeeded) in {wall:.1f} s; report: {args.out}")
    if args.json:
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())

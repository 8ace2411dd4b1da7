"""`gd2p eval suite`: every task family with the default and its baselines, one report with a table per task.

Each task is a closed-loop run of its own (`<out>/closed-loop-<world>...[-<task>]/`, resumable, extendable by
method like any run; the paper's task is the closed-loop experiment itself), so a suite re-run only adds what is
missing. The suite's report (`<out>/suite-<world>...`) reads those runs' records: per task, each method's success
with its interval clustered by object and the default's paired difference to each baseline; then the suite over
all tasks (every trial of every task pooled, clustered by object). Methods get the same budget and stages
(docs/evaluation.md, "Tasks").
"""
from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from evaluation import tolerance
from evaluation.methods import DEFAULT_METHOD, failure_cause, protocol_for, run_protocol
from evaluation.report import markdown_table, write_experiment
from evaluation.stats import difference_interval, success_interval
from evaluation.store import RECORDS_FILE, read_records
from evaluation.tasks import TASK_CRITERIA, TASKS
from shared.execution.robots import TrackingMode
from shared.world.sim.world import WorldLevel

# The baselines, each with the default's budget and stages: retrieval (nearest neighbour) with every stage, the
# fixed spatula pose with corrective pushes, and a straight-line pusher (one fingertip) with corrective pushes.
SUITE_METHODS = (DEFAULT_METHOD, "nearest-closed-critic", "fixed-corrected", "fingertip-corrected")


def run_suite(out: Path, quick: bool = False, workers: int = 2, trials: int | None = None, world: WorldLevel = "real",
              methods: Sequence[str] | None = None, cameras: int = 0, split: str = "test", tag: str | None = None,
              worker_init: Callable[[str], None] | None = None, tracking: TrackingMode = "image",
              tasks: Sequence[str] = TASKS) -> Path:
    """Run every task of `tasks` (each a closed-loop run), then write the suite's report; its path."""
    unknown = [t for t in tasks if t not in TASKS]
    if unknown or not tasks:
        raise ValueError(f"unknown task(s) {unknown}; known: {', '.join(TASKS)}")
    methods = tuple(methods or SUITE_METHODS)
    started = time.perf_counter()
    runs: dict[str, Path] = {}
    for task in tasks:
        report = run_protocol("closed-loop", out, quick, workers, trials, world, methods, cameras, split, tag,
                              worker_init, tracking, task=task)
        runs[task] = report.parent
    specs = {task: replace(protocol_for("closed-loop", quick, trials, world, methods, cameras, split, tag, task),
                           tracking=tracking) for task in tasks}
    records = {task: _records(runs[task], specs[task]) for task in tasks}
    directory = Path(out) / replace(specs[tasks[0]], name="suite", task="paper").directory_name
    body = suite_body(records, runs, methods)
    summary = {"tasks": {task: _summary(records[task], methods) for task in tasks},
               "suite": _summary([r for rs in records.values() for r in rs], methods),
               "runs": {task: runs[task].name for task in tasks}, "methods": list(methods)}
    title = f"Suite: {', '.join(tasks)} (Allegro + Panda), world `{world}`"
    flat = [r for rs in records.values() for r in rs]
    return write_experiment(directory, title, body, summary, time.perf_counter() - started, quick, flat)


def _records(directory: Path, spec: Any) -> list[dict[str, Any]]:
    """The run's records of `spec`'s episodes (all present: the run just finished them)."""
    stored = read_records(directory / RECORDS_FILE)
    return [stored[e.key] for e in spec.episodes()]


def _summary(records: Sequence[dict[str, Any]], methods: Sequence[str]) -> dict[str, Any]:
    by_method = {m: [r for r in records if r["method"] == m] for m in methods}
    out: dict[str, Any] = {m: {"trials": len(rs), "interval_95": success_interval(rs).as_dict()}
                           for m, rs in by_method.items()}
    if DEFAULT_METHOD in by_method:
        out["differences_95"] = {f"{DEFAULT_METHOD} - {m}": difference_interval(by_method[DEFAULT_METHOD], rs).as_dict()
                                 for m, rs in by_method.items() if m != DEFAULT_METHOD}
    return out


def suite_body(records: dict[str, list[dict[str, Any]]], runs: dict[str, Path], methods: Sequence[str]) -> str:
    """The report: a table per task (success, objects, the default's paired difference, failure causes) and its
    success against the tolerance, then the suite pooled."""
    parts = []
    for task, rs in records.items():
        objects = len({r["object_id"] for r in rs})
        by_method = {m: tolerance.curves([r for r in rs if r["method"] == m]) for m in methods}
        parts.append(f"## Task `{task}`\n\n{TASK_CRITERIA[task]}. {objects} objects; trials in "
                     f"[{runs[task].name}](../{runs[task].name}/report.md).\n\n" + _table(rs, methods)
                     + "\nAgainst the tolerance (the same trials; the turn is the one the task judges):\n\n"
                     + tolerance.table(by_method))
    pooled = [r for rs in records.values() for r in rs]
    parts.append("## The suite\n\nEvery trial of every task pooled; intervals clustered by object.\n\n"
                 + _table(pooled, methods))
    return "\n".join(parts)


def _table(records: Sequence[dict[str, Any]], methods: Sequence[str]) -> str:
    rows = []
    default = [r for r in records if r["method"] == DEFAULT_METHOD]
    for method in methods:
        rs = [r for r in records if r["method"] == method]
        difference = ("" if method == DEFAULT_METHOD or not default
                      else difference_interval(default, rs).points())
        causes = Counter(c for c in map(failure_cause, rs) if c is not None)
        rows.append([method, len(rs), str(success_interval(rs)), difference,
                     ", ".join(f"{c} {n}" for c, n in causes.most_common()) or "–"])
    return markdown_table(["method", "trials", "success [95% CI]", f"{DEFAULT_METHOD} minus it (points) [95% CI]",
                           "failures by cause"], rows)


# ----------------------------------------------------------------------------------------------- the tasks, drawn
SCENE_DIRECTION_DEG = 60.0  # the protocol's first direction
NEIGHBOUR_RGBA = (0.55, 0.55, 0.58, 1.0)
WALL_RGBA = (0.80, 0.15, 0.15, 1.0)


def task_scene(task: str, trial: int = 0) -> tuple[list[Any], float]:
    """What a task's first trial puts on the table (its first object where it is truly put down, the wall or the
    neighbours, the push and the target's tolerance), as render items; and the push's heading (degrees)."""
    from evaluation import push_protocol as protocol
    from shared.frames import direction_frame, direction_xy
    from shared.world.obstacles import obstacle_mesh
    from visualisation.render import mesh_item, push_markers

    objects = protocol_for("closed-loop", False, 1, "real", None, 3, "test", None, task).objects
    episode = protocol.Episode(DEFAULT_METHOD, "allegro", objects[0], SCENE_DIRECTION_DEG, trial, cameras=3, task=task)
    T = protocol.put_down(episode, protocol.execution_world(episode))
    items: list[Any] = [mesh_item("object", protocol.load_object(episode.object_id).mesh, T)]
    items += [mesh_item(f"wall {k}", obstacle_mesh(o), np.eye(4), WALL_RGBA) for k, o in enumerate(protocol.task_obstacles(episode))]
    items += [mesh_item(f"neighbour {k}", protocol.load_object(ref.library_id).mesh, T_n, NEIGHBOUR_RGBA)
              for k, (ref, T_n) in enumerate(protocol.task_neighbours(episode)) if ref.library_id is not None]
    tolerance = 0.02 if task == "pose" else 0.03
    items += push_markers(direction_frame(T[:3, 3], direction_xy(SCENE_DIRECTION_DEG)), protocol.PUSH_DISTANCE_M, tolerance)
    return items, SCENE_DIRECTION_DEG


def draw_tasks(out: Path, tasks: Sequence[str] = TASKS) -> Path:
    """One picture of every task's first trial, seen from behind the push and above (`docs/img/suite_tasks.png`)."""
    from visualisation.render import LegendEntry, View, compose_png, render_views

    rendered = []
    for task in tasks:
        items, heading = task_scene(task)
        view = View(task, -180.0, 50.0, 24.0, label=task)
        rendered += render_views(items, [view], size=(360, 300), heading_deg=heading)
    legend = [LegendEntry("object", (0.42, 0.55, 0.78, 1.0)), LegendEntry("wall", WALL_RGBA),
              LegendEntry("neighbour", NEIGHBOUR_RGBA), LegendEntry("push and target", (0.12, 0.12, 0.12, 1.0))]
    return compose_png(rendered, out, title="The suite's tasks · each task's first trial, where its object is put down · "
                       f"push along {SCENE_DIRECTION_DEG:g}°", legend=legend, columns=3)


def main(argv: Sequence[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m evaluation.suite", description="Draw the suite's tasks (one "
                                     "picture: each task's first trial on the development split).")
    parser.add_argument("--draw", type=Path, required=True, metavar="PNG", help="where to write the picture")
    parser.add_argument("--tasks", default=",".join(TASKS), help="comma-separated tasks (default all)")
    args = parser.parse_args(argv)
    tasks = [t.strip() for t in args.tasks.split(",") if t.strip()]
    unknown = [t for t in tasks if t not in TASKS]
    if unknown or not tasks:
        parser.error(f"unknown task(s) {unknown}; known: {', '.join(TASKS)}")
    print(draw_tasks(args.draw, tasks))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

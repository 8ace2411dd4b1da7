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

"""Two evaluation runs of one protocol, trial by trial: `gd2p compare RUN_A[:METHOD] RUN_B[:METHOD]`.

A run is a `gd2p eval methods|leap|closed-loop` results directory (its `records.jsonl`). Trials are
matched by what makes them the same episode: object, direction, trial index, the episode seed and the
execution world's draw. Only matched trials are compared, so a run with 3 trials per cell compares
with the first 3 of a run with 5, and the difference is paired: the bootstrap draws the same objects
for both runs (`evaluation.stats.difference_interval`). Use it to ask whether another checkpoint,
other ranking weights or new code changed the outcome of the same trials.

With `--across-worlds` trials are matched by the request alone (object, direction, trial index and episode
seed: the same told start pose), whatever world executed them: a `real` run against the `exact` run of the
same protocol then says what the world the planner does not know costs each method, paired by object.

`gd2p eval sampler-quality` runs compare the same way, object by object (`DIR:ddpm100-critic`): an object is the
same episode in both runs when its execution world is the same draw, and each of its pushed poses counts as a
trial of the validated fraction (`evaluation.coverage.pose_trials`). So the same source under two success
critics, or two checkpoints, pair up on the objects both measured in the same worlds.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from evaluation.report import markdown_table
from evaluation.stats import difference_interval, success_interval
from evaluation.store import RECORDS_FILE, read_records

DEFAULT_METHOD = "gd2p"


class CompareError(ValueError):
    """A run that cannot be read or compared, with the reason."""


@dataclass(frozen=True)
class RunRecords:
    """One method's trials of one run."""

    directory: Path
    method: str
    records: tuple[dict[str, Any], ...]

    @property
    def label(self) -> str:
        return f"{self.directory.name}:{self.method}"


def parse_run(spec: str) -> tuple[Path, str]:
    """`DIR` or `DIR:METHOD` -> (directory, method); the method defaults to gd2p."""
    directory, _, method = spec.partition(":")
    if not directory:
        raise CompareError(f"{spec!r}: give a results directory, e.g. results/methods-real:gd2p")
    return Path(directory), method or DEFAULT_METHOD


def load_run(directory: Path, method: str) -> RunRecords:
    """The finished trials of `method` in `directory`, read as the result store reads them."""
    path = directory / RECORDS_FILE
    if not path.is_file():
        raise CompareError(f"{directory}: no {RECORDS_FILE} (not a `gd2p eval` run)")
    everything = read_records(path).values()
    records = [r for r in everything if _method(r) == method]
    if not records:
        methods = sorted({_method(r) for r in everything})
        raise CompareError(f"{directory}: no trials of method {method!r}; it has: {', '.join(methods) or 'none'}")
    return RunRecords(directory, method, tuple(records))


def _method(record: dict[str, Any]) -> str:
    """A trial's method; a sampler-quality record names its source in its key ("ddpm100-critic/proc-box-003")."""
    return str(record["method"]) if "method" in record else str(record.get("key", "")).split("/")[0]


def _is_coverage(run: RunRecords) -> bool:
    return all("fraction_pushed" in r for r in run.records)


def request_key(record: dict[str, Any]) -> tuple:
    """What the planner is asked: where, which way, which trial (its seed places the object it is told of)."""
    return (record["hand"], record["object_id"], float(record["direction_deg"]), int(record["trial"]),
            record.get("seed"))


def episode_key(record: dict[str, Any]) -> tuple:
    """What makes two trials the same episode: the same request executed in the same drawn world."""
    draw = record.get("world_draw") or {}
    return request_key(record) + (record.get("world", "exact"), draw.get("seed"))


def matched(a: RunRecords, b: RunRecords, across_worlds: bool = False) -> tuple[list[dict[str, Any]],
                                                                                list[dict[str, Any]]]:
    """The trials of `a` and `b` that are the same episode (the same request, if `across_worlds`), in order."""
    key = request_key if across_worlds else episode_key
    by_key = {key(r): r for r in b.records}
    pairs = [(r, by_key[key(r)]) for r in a.records if key(r) in by_key]
    return [p[0] for p in pairs], [p[1] for p in pairs]


def _described(records: list[dict[str, Any]], field: str) -> str:
    values = Counter(str(r.get(field, "not recorded")) for r in records)
    return ", ".join(f"{v} ({n})" for v, n in values.items())


def compare(a: RunRecords, b: RunRecords, across_worlds: bool = False, command: str | None = None) -> str:
    """A markdown report: each run on the shared episodes (requests, if `across_worlds`), B − A paired by
    object, and where they differ; headed by the `command` that made it, when given."""
    if _is_coverage(a) or _is_coverage(b):
        return compare_coverage(a, b, across_worlds, command)
    shared_a, shared_b = matched(a, b, across_worlds)
    if not shared_a:
        what = "request (object, direction, trial and seed)" if across_worlds else \
            "episode (object, direction, trial, seed and world draw)"
        raise CompareError(f"{a.label} and {b.label} share no {what}: they are not runs of the same protocol")
    same = "request, each executed in its run's world," if across_worlds else "episode"
    rows = [[run.label, len(shared), str(success_interval(shared)), _described(shared, "world"),
             _described(shared, "pose_model"), _described(shared, "ranking_weights"), _described(shared, "code")]
            for run, shared in ((a, shared_a), (b, shared_b))]
    table = markdown_table(["run:method", "shared trials", "success [95% CI]", "world", "pose model",
                            "ranking weights (α, β, γ)", "code"], rows)
    outcomes = Counter((bool(x["success"]), bool(y["success"])) for x, y in zip(shared_a, shared_b, strict=True))
    objects = len({r["object_id"] for r in shared_a})
    return (f"# {b.label} against {a.label}\n\n" + (f"- command: `{command}`\n\n" if command else "")
            + f"{len(shared_a)} trials are the same {same} in both runs ({objects} objects; of {len(a.records)} and "
            f"{len(b.records)} trials). Intervals: 95%, bootstrap clustered by object.\n\n{table}\n"
            f"**B − A, paired by object: {difference_interval(shared_b, shared_a).points()} points.**\n\n"
            f"| both succeed | only A | only B | both fail |\n|---|---|---|---|\n"
            f"| {outcomes[(True, True)]} | {outcomes[(True, False)]} | {outcomes[(False, True)]} | "
            f"{outcomes[(False, False)]} |\n")


def _world_of(record: dict[str, Any]) -> str:
    world = record.get("world") or {}
    return f"{world.get('level', 'exact')}, {world.get('cameras', 0)} cameras"


def compare_coverage(a: RunRecords, b: RunRecords, across_worlds: bool = False, command: str | None = None) -> str:
    """`compare` for two sampler-quality sources: the objects measured in the same drawn world by both (the same
    object alone, if `across_worlds`), each pushed pose a trial, B − A paired by object."""
    from evaluation.coverage import pose_trials

    if not (_is_coverage(a) and _is_coverage(b)):
        raise CompareError(f"{a.label} and {b.label}: a sampler-quality run compares only with another")

    def key(record: dict[str, Any]) -> tuple:
        return (record["object"],) if across_worlds else (record["object"], (record.get("world") or {}).get("seed"))

    by_key = {key(r): r for r in b.records}
    pairs = [(r, by_key[key(r)]) for r in a.records if key(r) in by_key]
    if not pairs:
        raise CompareError(f"{a.label} and {b.label} share no object measured in the same world")
    shared = {"A": [p[0] for p in pairs], "B": [p[1] for p in pairs]}
    trials = {side: pose_trials(records) for side, records in shared.items()}
    rows = [[run.label, len(shared[side]), str(success_interval(trials[side])), _described(shared[side], "code"),
             ", ".join(f"{w} ({n})" for w, n in Counter(_world_of(r) for r in shared[side]).items())]
            for side, run in (("A", a), ("B", b))]
    table = markdown_table(["run:source", "shared objects", "validated fraction [95% CI]", "code", "world"], rows)
    rates = [(x["fraction_successes"] / max(x["fraction_pushed"], 1), y["fraction_successes"] / max(y["fraction_pushed"], 1))
             for x, y in pairs]
    same = "object" if across_worlds else "object in the same drawn world"
    return (f"# {b.label} against {a.label}\n\n" + (f"- command: `{command}`\n\n" if command else "")
            + f"{len(pairs)} objects are the same {same} in both runs (of {len(a.records)} and {len(b.records)}); "
            f"each pushed pose of the validated-fraction window is a trial. Intervals: 95%, bootstrap clustered by "
            f"object.\n\n{table}\n"
            f"**B − A, paired by object: {difference_interval(trials['B'], trials['A']).points()} points.**\n\n"
            f"| objects where B validates more | where A does | equal |\n|---|---|---|\n"
            f"| {sum(y > x for x, y in rates)} | {sum(x > y for x, y in rates)} | {sum(x == y for x, y in rates)} |\n")

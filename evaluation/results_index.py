"""The results index, generated: `results/README.md` (one row per run kept in the tree) and `docs/results.md`
(the figures a user cares about, per experiment), both written from the runs' `summary.json`.

    python -m evaluation.results_index               # rewrite both files
    python -m evaluation.results_index --check       # exit 1 when either differs from what would be written
    python -m evaluation.results_index --superseded  # the runs to `git rm`: not cited, not the newest of their experiment

An *experiment* is what a run's directory and settings name apart from its `--tag` (`methods.Protocol.directory_name`,
`multistep.run`, `sampler_quality.result_directory`, `data_size.result_directory`): the experiment (methods, leap,
closed-loop, multistep open or closed loop, sampler-quality per hand and placement, data-size), the world, the cameras
and the split. A tagged run is another run of the same experiment (other models or code); the tree keeps the newest
run of each experiment (by the date its summary records) and the runs the documentation or the code cite by path;
git history keeps the rest. `gd2p eval` rewrites the index of its `--out` directory after each experiment.
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from evaluation.report import REPORT_FILE, SUMMARY_FILE, markdown_table
from evaluation.stats import Interval, success_interval
from evaluation.store import RECORDS_FILE, SETTINGS_FILE, read_records
from evaluation.tasks import TASKS
from shared.atomic import atomic_write_text

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "results"
DOCS_RESULTS = ROOT / "docs" / "results.md"
COMMAND = "python -m evaluation.results_index"
DOCS_MAX_LINES = 150
# Where a run may be cited by path (`--superseded` keeps what these name).
CITING = ("README.md", "CONTRIBUTING.md", "docs", "evaluation", "bench", "tests", "cli", "services", "shared", "deploy")
EXPERIMENT_ORDER = (
    "suite",
    "methods",
    "leap",
    "closed-loop",
    "multistep",
    "sampler-quality",
    "data-size",
    "sampler-diagnosis",
    "dataset build",
)
SPLIT_ORDER = ("final", "test", "unseen", "val", "train")

_PROTOCOL = re.compile(
    r"^(methods|leap|closed-loop|suite)(?:-(real|exact|mujoco))?(?:-camera(\d))?(-truthtrack)?(?:-(val|unseen|final))?"
    rf"(?:-({'|'.join(t for t in TASKS if t != 'paper')}))?(?:-(.+))?$"
)
_MULTISTEP = re.compile(r"^multistep(?:-(real|exact))?(?:-closed)?(?:-camera(\d))?(?:-(val))?(?:-(.+))?$")
_COVERAGE = re.compile(
    r"^(sampler-quality|data-size)(?:-(real|exact)(?:-camera(\d))?)?(-val)?(-random-yaw)?(?:-(.+))?$"
)


@dataclass(frozen=True)
class Row:
    """One figure of a run: a method (or model, or fraction of the data) and its rate."""

    label: str
    rate: Interval | None  # value with its 95% interval clustered by object (low = high = nan: no interval recorded)
    count: int  # trials, runs or objects the rate is over


@dataclass
class Run:
    name: str
    path: Path
    summary: dict[str, Any]
    settings: dict[str, Any]
    experiment: str = ""
    hand: str = "allegro"
    world: str = "exact"
    cameras: int = 0
    split: str = "test"
    variant: str = ""  # what else names the experiment: closed loop, the placement's yaw
    tag: str = ""
    rows: list[Row] = field(default_factory=list)
    metric: str = "success"
    unit: str = "trials"

    @property
    def key(self) -> tuple[str, ...]:
        """The experiment this run is a run of."""
        return (self.experiment, self.hand, self.world, str(self.cameras), self.split, self.variant)

    @property
    def date(self) -> str:
        return str(self.summary.get("date", ""))

    @property
    def seen(self) -> str:
        if self.world == "exact" or not self.cameras:
            return f"{self.world}, told the mesh"
        return f"{self.world}, {self.cameras} camera{'s' * (self.cameras > 1)}"

    @property
    def link(self) -> str:
        return f"{self.name}/{REPORT_FILE}" if (self.path / REPORT_FILE).exists() else f"{self.name}/"

    @property
    def commit(self) -> str:
        """The commits that ran the trials (with their counts when several did), else the one that wrote the report."""
        stamps = self.summary.get("records_code")
        if stamps:
            ranked = sorted(stamps.items(), key=lambda item: (-item[1], item[0]))
            return ranked[0][0] if len(ranked) == 1 else ", ".join(f"{c} ({n})" for c, n in ranked)
        return str(self.summary.get("code") or "not recorded")

    @property
    def command(self) -> str:
        """The recorded command without where it wrote and how many processes it used."""
        try:
            words = shlex.split(str(self.summary.get("command", "")))
        except ValueError:
            return str(self.summary.get("command", ""))
        kept: list[str] = []
        skip = False
        for word in words:
            if skip:
                skip = False
            elif word in ("--out", "--workers"):
                skip = True
            elif not word.startswith(("--out=", "--workers=")):
                kept.append(word)
        return " ".join(shlex.quote(w) for w in kept)

    @property
    def seeds(self) -> str:
        coverage = self.settings.get("coverage", self.settings)
        if self.experiment == "data-size" and self.settings.get("seeds") is not None:
            return (
                f"training seeds {', '.join(str(s) for s in self.settings['seeds'])}, "
                f"sampling seed {coverage.get('seed', 0)}"
            )
        if self.experiment in ("sampler-quality", "sampler-diagnosis"):
            seed = coverage.get("seed", coverage.get("selection_seed", 0))
            return f"seed {seed} (poses and placement drawn per object from it)"
        if self.experiment in ("methods", "leap", "closed-loop"):
            cells = len(self.settings.get("objects", ())) * len(self.settings.get("directions_deg", ()))
            trials = max((r.count for r in self.rows), default=0)
            per_cell = f", {trials // cells} per object and direction" if cells and trials % cells == 0 else ""
            return f"one per trial, from its object, direction and index{per_cell}; the same for every method"
        if self.experiment == "multistep":
            return "one per run, from its scenario, object and trial"
        return "–"


def _interval(entry: dict[str, Any]) -> Interval:
    return Interval(float(entry["value"]), float(entry["low"]), float(entry["high"]))


def _no_interval(value: float) -> Interval:
    return Interval(float(value), float("nan"), float("nan"))


def _ordered_methods(summary: dict[str, Any], methods: Sequence[str]) -> list[str]:
    """The methods in the order the command gave them (the one a run was made for first), then the rest."""
    words = str(summary.get("command", "")).split()
    given = words[words.index("--methods") + 1].split(",") if "--methods" in words[:-1] else []
    first = [m for m in given if m in methods]
    return first + sorted((m for m in methods if m not in first), key=lambda m: (not m.startswith("gd2p"), m))


def _protocol_rows(run: Run) -> list[Row]:
    methods = run.summary.get("methods") or {}
    records: list[dict[str, Any]] | None = None
    rows = []
    for method in _ordered_methods(run.summary, list(methods)):
        entry = methods[method]
        if "interval_95" in entry:
            rate = _interval(entry["interval_95"])
        else:  # runs from before intervals were recorded: the same bootstrap over their records
            if records is None:
                path = run.path / RECORDS_FILE
                records = list(read_records(path).values()) if path.exists() else []
            mine = [r for r in records if r.get("method") == method]
            rate = success_interval(mine) if mine else _no_interval(entry["success_rate"])
        rows.append(Row(method, rate, int(entry.get("trials", 0))))
    return rows


def _suite_rows(run: Run) -> list[Row]:
    """A suite's methods over every task's trials pooled (`evaluation.suite`)."""
    pooled = run.summary.get("suite") or {}
    methods = [m for m in run.summary.get("methods", []) if m in pooled]
    return [Row(m, _interval(pooled[m]["interval_95"]), int(pooled[m]["trials"])) for m in methods]


def _coverage_rows(run: Run) -> list[Row]:
    methods = run.summary.get("methods") or {}
    rows = []
    for label in _ordered_labels(run.summary, list(methods)):
        entry = methods[label]
        ci = entry.get("pooled_validated_fraction_ci")
        value = float(entry["pooled_validated_fraction"])
        rows.append(
            Row(
                label,
                Interval(value, float(ci[0]), float(ci[1])) if ci else _no_interval(value),
                int(entry.get("objects", 0)),
            )
        )
    return rows


def _ordered_labels(summary: dict[str, Any], labels: Sequence[str]) -> list[str]:
    return sorted(labels, key=lambda label: (not label.startswith("DDPM"), label))


def _data_size_rows(run: Run) -> list[Row]:
    objects = int(run.settings.get("test_objects", 0))
    rows = []
    for entry in sorted(run.summary.get("per_fraction", ()), key=lambda e: -float(e["fraction"])):
        rate = (
            _interval(entry["validated_fraction"])
            if isinstance(entry.get("validated_fraction"), dict)
            else _no_interval(entry["validated_fraction_mean"])
        )
        rows.append(Row(f"{float(entry['fraction']):.0%} of the data", rate, objects))
    return rows


def _diagnosis_rows(run: Run) -> list[Row]:
    rows = []
    for group in ("held_out", "trained"):
        question = run.summary.get("question_1", {}).get(group, {})
        for source in ("diffusion", "stored"):
            if source in question:
                rows.append(
                    Row(
                        f"{source}, {group.replace('_', '-')} objects",
                        _interval(question[source]["interval_95"]),
                        int(question.get("objects", 0)),
                    )
                )
    return rows


def describe(path: Path) -> Run:
    """A run directory as the index shows it: its experiment, setting and figures."""
    summary_path, settings_path = path / SUMMARY_FILE, path / SETTINGS_FILE
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    settings = json.loads(settings_path.read_text()) if settings_path.exists() else {}
    run = Run(path.name, path, summary, settings)
    name = path.name
    if match := _PROTOCOL.match(name):
        run.experiment, run.world, cameras, split, run.tag = (
            match[1],
            match[2] or "exact",
            match[3],
            match[5],
            match[7] or "",
        )
        run.variant = ", ".join(v for v in (match[6] and f"task {match[6]}", match[4] and "truth tracker") if v)
        run.cameras, run.split = int(settings.get("cameras") or cameras or 0), split or "test"
        run.hand = str(settings.get("hand", "leap" if run.experiment == "leap" else "allegro"))
        run.rows = _suite_rows(run) if run.experiment == "suite" else _protocol_rows(run)
    elif match := _MULTISTEP.match(name):
        run.experiment, run.world, cameras, split, run.tag = (
            "multistep",
            match[1] or "exact",
            match[2],
            match[3],
            match[4] or "",
        )
        run.cameras, run.split = int(settings.get("cameras") or cameras or 0), split or "test"
        closed = bool(settings.get("closed_loop"))
        run.variant = "closed loop" if closed else "open loop"
        run.unit = "runs"
        if "success_rate" in summary:
            rate = (
                _interval(summary["interval_95"]) if "interval_95" in summary else _no_interval(summary["success_rate"])
            )
            run.rows = [Row("gd2p, every push watched" if closed else "gd2p", rate, int(summary.get("runs", 0)))]
    elif match := _COVERAGE.match(name):
        run.experiment, run.world, cameras, val, random_yaw, run.tag = (
            match[1],
            match[2] or "exact",
            match[3],
            match[4],
            match[5],
            match[6] or "",
        )
        run.cameras, run.split = int(cameras or 0), "val" if val else "test"
        coverage = settings.get("coverage", settings)
        run.hand = str(
            summary.get("hand")
            or coverage.get("hand")
            or ("leap" if "leap" in run.tag or "leap" in str(summary.get("checkpoint", "")) else "allegro")
        )
        run.variant = "random yaw" if random_yaw else "yaw 0"
        run.metric, run.unit = "validated fraction", "objects"
        run.rows = _data_size_rows(run) if run.experiment == "data-size" else _coverage_rows(run)
    elif name == "sampler-diagnosis":
        run.experiment, run.metric, run.unit = "sampler-diagnosis", "validated fraction", "objects"
        run.rows = _diagnosis_rows(run)
    elif summary:  # an experiment this index does not know yet: its name is its experiment
        run.experiment = name
    else:  # a record of how a committed dataset was built (no summary)
        run.experiment, run.hand, run.split = "dataset build", "leap" if "leap" in name else "allegro", "train"
    return run


def is_run(path: Path) -> bool:
    """Whether a directory under results/ is a run the index lists."""
    # results/final/ holds the final split's run log (LOG.md), not a run; an empty directory (a run
    # that wrote nothing yet) is not in a clone, since git carries no empty directories
    return path.is_dir() and path.name != "final" and any(path.iterdir())


def read_runs(out: Path = RESULTS) -> list[Run]:
    """Every run directory under `out`, in the index's order."""
    runs = [describe(p) for p in sorted(Path(out).iterdir()) if is_run(p)]

    def order(run: Run) -> tuple[Any, ...]:
        kind = EXPERIMENT_ORDER.index(run.experiment) if run.experiment in EXPERIMENT_ORDER else len(EXPERIMENT_ORDER)
        return (kind, run.hand, SPLIT_ORDER.index(run.split), run.world != "real", -run.cameras, run.variant, run.name)

    return sorted(runs, key=order)


def newest(runs: Sequence[Run]) -> dict[tuple[str, ...], Run]:
    """The newest run of each experiment (by the date its summary records; the name breaks a tie)."""
    latest: dict[tuple[str, ...], Run] = {}
    for run in sorted(runs, key=lambda r: (r.date, r.name)):
        latest[run.key] = run
    return latest


def cited(runs: Sequence[Run], root: Path = ROOT) -> set[str]:
    """The runs some file of the repository names by path (`results/<run>`), outside results/ itself."""
    names = {r.name for r in runs}
    pattern = re.compile(r"results/([A-Za-z0-9._-]+)")
    found: set[str] = set()
    for top in CITING:
        base = root / top
        files = [base] if base.is_file() else [p for p in base.rglob("*") if p.suffix in (".py", ".md", ".txt")]
        for path in files:
            try:
                text = path.read_text()
            except (OSError, UnicodeDecodeError):
                continue
            found.update(m.rstrip(".") for m in pattern.findall(text))
    return names & found


def superseded(runs: Sequence[Run], root: Path = ROOT) -> list[str]:
    keep = {r.name for r in newest(runs).values()} | cited(runs, root)
    return sorted(r.name for r in runs if r.name not in keep)


def _figure(row: Row) -> str:
    return (
        f"{row.rate}"
        if row.rate is not None and row.rate.low == row.rate.low
        else (f"{row.rate.value:.1%} (no interval recorded)" if row.rate is not None else "–")
    )


def _split(run: Run) -> str:
    # the library's test split is the development split; final: the final split
    return {"test": "development", "val": "val (tuning)", "unseen": "unseen family", "final": "final"}.get(
        run.split, run.split
    )


def _experiment(run: Run) -> str:
    extra = [run.hand] if run.experiment in ("sampler-quality", "data-size", "dataset build") else []
    extra += [run.variant] if run.variant else []
    return run.experiment + (f" ({', '.join(extra)})" if extra else "")


def _heading(run: Run) -> str:
    """The report's title, with what it leaves out (the hand, the world, the placement)."""
    title = str(run.summary.get("title", run.name))
    if run.experiment not in ("sampler-quality", "data-size"):
        return title
    extra = [run.hand, f"world `{run.world}`" + (f", {run.cameras} cameras" if run.cameras else "")]
    return f"{title} ({', '.join(extra + [run.variant])})"


def _docs_heading(run: Run) -> str:
    """The heading of a run's section on docs/results.md: its report's title, and whether it is the final split."""
    heading = _heading(run)
    return heading if run.split != "final" or "final split" in heading else f"{heading} — final split"


def render_index(runs: Sequence[Run]) -> str:
    rows = []
    for run in runs:
        head = run.rows[0] if run.rows else None
        methods = (
            "; ".join(r.label for r in run.rows)
            if run.experiment not in ("data-size",)
            else (f"{len(run.rows)} data fractions" if run.rows else "–")
        )
        counts = sorted({r.count for r in run.rows})
        trials = (
            "–"
            if not counts
            else (
                f"{counts[0]} {run.unit}" + (" each" if len(run.rows) > 1 else "")
                if len(counts) == 1
                else f"{counts[0]}-{counts[-1]} {run.unit}"
            )
        )
        headline = f"{head.label}: {_figure(head)}" if head else "–"
        rows.append(
            [
                f"[{run.name}]({run.link})",
                _experiment(run),
                _split(run),
                run.seen if run.rows else "–",
                methods or "–",
                trials,
                headline,
                run.commit if run.summary else "–",
                run.date[:10] or "–",
            ]
        )
    table = markdown_table(
        ["run", "experiment", "split", "world", "method(s)", "trials", "headline [95% interval]", "commit", "date"],
        rows,
    )
    return (
        f"# Evaluation results\n\n"
        f"Generated by `{COMMAND}` from each run's `{SUMMARY_FILE}`: do not edit "
        f"(`tests/test_results_index.py` fails when it is stale). The figures a user cares about, per experiment: "
        f"[docs/results.md](../docs/results.md).\n\n"
        f"Each run is `<experiment>-<world>[-cameraN][-split][-tag]/`: `{REPORT_FILE}` (the full report), "
        f"`{SUMMARY_FILE}` (every figure), `{RECORDS_FILE}` (every trial) and `{SETTINGS_FILE}`; `gd2p eval` writes "
        f"them. The tree keeps the runs the documentation and the code cite and the newest run of each experiment; "
        f"the others are in git history (`git log --diff-filter=D --stat -- results/`). Headline: the first method "
        f"of the run's command, its success rate (sampler-quality, data-size, sampler-diagnosis: the share of "
        f"sampled poses that push the object as asked) with its 95% interval clustered by object. Commit: the "
        f"commits that ran the trials (trials per commit when several did).\n\n" + table
    )


def _docs_runs(runs: Sequence[Run]) -> list[Run]:
    """The runs a user cares about: of each experiment in the evaluation's default setting (the `real` world seen by
    3 cameras, the image tracker) on the final split (first: the held-out figures), the development objects and
    the never-trained family, the newest run that compares methods (a run of one method, such as one side of an
    A/B, does not stand in for it, nor does an A/B of the default against a tuning candidate or ablation of
    evaluation/methods.yaml); a suite's task runs are in its section (pooled) and its report."""
    from evaluation.push_protocol import load_methods

    tuning = {name for name, method in load_methods().items() if method.tuning}
    shown: dict[tuple[str, ...], Run] = {}
    for run in sorted(runs, key=lambda r: (len(r.rows) > 1, r.date, r.name)):
        if not any(row.label in tuning for row in run.rows):
            shown[run.key] = run
    default = [
        r
        for r in shown.values()
        if r.rows and r.world == "real" and r.cameras == 3 and r.split in ("final", "test", "unseen")
        and "task " not in r.variant and "truth tracker" not in r.variant
    ]
    order = {r.name: i for i, r in enumerate(runs)}
    return sorted(default, key=lambda r: (r.split != "final", order[r.name]))


def render_docs(runs: Sequence[Run]) -> str:
    lines = [
        "# Results",
        "",
        (
            f"Generated by `{COMMAND}` from the runs' `{SUMMARY_FILE}`: do not edit. Each section is the newest run "
            "comparing methods of an experiment in the evaluation's default setting: executed in a world drawn per trial that the planner "
            "does not know (`--world real`), the object seen by 3 simulated depth cameras, on the final split (held "
            "out, measured once per release: the sections marked so, first), the 14 development objects (the "
            "library's `test` split, run after most changes) or a shape family no model trains on (`--split unseen`). "
            "Every rate has its 95% interval, bootstrapped over "
            "objects (trials of one object are not independent). Every kept run, with the tuning (`val`) runs, the "
            "planner's own world and earlier models: [results/README.md](../results/README.md); the protocol: "
            "`gd2p eval --help`."
        ),
        "",
    ]
    for run in _docs_runs(runs):
        lines += [
            f"## {_docs_heading(run)}",
            "",
            (
                f"`{run.command}` · commit {run.commit} · {run.date[:10]} · seeds: {run.seeds} · "
                f"[report](../results/{run.link})"
            ),
            "",
        ]
        header = {"success": "success [95% interval]", "validated fraction": "poses validated [95% interval]"}[
            run.metric
        ]
        lines += markdown_table(
            ["method" if run.experiment != "data-size" else "training data", header, run.unit],
            [[r.label, _figure(r), r.count] for r in run.rows],
        ).splitlines()
        lines.append("")
    return "\n".join(lines).rstrip("\n") + "\n"


def write_index(out: str | Path = RESULTS) -> Path:
    """Rewrite `<out>/README.md`; for the repository's results/, docs/results.md too."""
    out = Path(out)
    runs = read_runs(out)
    path = atomic_write_text(out / "README.md", render_index(runs))
    if out.resolve() == RESULTS.resolve():
        atomic_write_text(DOCS_RESULTS, render_docs(runs))
    return path


def stale(out: Path = RESULTS, docs: Path = DOCS_RESULTS) -> list[Path]:
    """The generated files that differ from what would be written now."""
    runs = read_runs(out)
    wanted = {out / "README.md": render_index(runs), docs: render_docs(runs)}
    return [p for p, text in wanted.items() if not p.exists() or p.read_text() != text]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog=COMMAND, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--check", action="store_true", help="exit 1 when results/README.md or docs/results.md is stale"
    )
    parser.add_argument(
        "--superseded",
        action="store_true",
        help="print the runs neither cited by path nor the newest of their experiment (to git rm)",
    )
    args = parser.parse_args(argv)
    if args.superseded:
        print("\n".join(f"results/{name}" for name in superseded(read_runs())))
        return 0
    if args.check:
        old = stale()
        for path in old:
            print(f"{path.relative_to(ROOT)} is stale: run `{COMMAND}`", file=sys.stderr)
        return 1 if old else 0
    print(write_index(RESULTS))
    print(DOCS_RESULTS)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Writing an experiment's results: a Markdown report, a JSON summary, and the index `results/README.md`.

Each experiment writes `<out>/<experiment>/report.md` and `summary.json` (plots beside them);
`write_index` lists every run found under `<out>` in `<out>/README.md`, one row each (`evaluation.results_index`).
"""
from __future__ import annotations

import json
import os
import platform
import shlex
import subprocess
import sys
from collections import Counter
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from shared.atomic import atomic_write_text

REPORT_FILE = "report.md"
SUMMARY_FILE = "summary.json"


def machine() -> str:
    """One line naming the machine: CPU, core count, memory, OS, Python."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    memory = ""
    try:
        pages, page_size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
        memory = f", {pages * page_size / 2**30:.0f} GiB"
    except (ValueError, OSError, AttributeError):
        pass
    return f"{cpu}, {os.cpu_count()} cores{memory}, no GPU used, {platform.system()} {platform.release()}, Python {platform.python_version()}"


def code_version() -> str:
    """The git commit the results came from (`-dirty` when code differs from it), or "unknown" outside git.

    Changed files under results/ and docs/results.md do not make the code dirty: an evaluation writes there while
    it runs (the index of the repository's results/ is both), and the next run would otherwise be stamped dirty.
    """
    root = Path(__file__).resolve().parent.parent

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    commit = git("rev-parse", "--short", "HEAD")
    if not commit:
        return "unknown"
    changed = git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)results",
                  ":(exclude)docs/results.md")
    return commit + ("-dirty" if changed else "")


CODE_AT_START = code_version()  # what this process loaded: a commit made while a long run goes on is not its code


def command_line() -> str:
    """The command as the user typed it (`gd2p eval ...`)."""
    argv = list(sys.argv)
    argv[0] = "gd2p" if Path(argv[0]).name in ("gd2p", "main.py", "__main__.py") else argv[0]
    return " ".join(shlex.quote(a) for a in argv)


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub Markdown table; floats with two decimals unless already formatted."""

    def cell(value: Any) -> str:
        if isinstance(value, float):
            return f"{value:.2f}"
        return str(value)

    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def write_experiment(directory: str | os.PathLike, title: str, body_markdown: str, summary: dict[str, Any],
                     wall_time_s: float, quick: bool, records: Sequence[dict[str, Any]] = ()) -> Path:
    """Write report.md and summary.json of one experiment; returns the report's path. `records`: the
    trials reported, whose own code stamps (`record["code"]`) the header counts."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    total = wall_time_s + _earlier_wall_time(directory)
    meta: dict[str, Any] = {"command": command_line(), "wall_time_s": round(total, 1), "last_invocation_s": round(wall_time_s, 1),
            "machine": machine(), "code": CODE_AT_START, "quick": quick,
            "date": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")}
    if records:
        meta["records_code"] = dict(Counter(r.get("code", "not recorded") for r in records))
        if any(r.get("pose_model") for r in records):
            meta["records_pose_model"] = dict(Counter(r["pose_model"] for r in records if r.get("pose_model")))
        if any("ranking_weights" in r for r in records):
            meta["records_ranking_weights"] = dict(Counter(str(r.get("ranking_weights", "not recorded"))
                                                           for r in records))
    resumed = f" summed over the invocations that ran (this one {wall_time_s / 60:.1f} min)" if total - wall_time_s >= 1 else ""
    made_by = ("\n- trials run by code: " + ", ".join(f"{c} ({n})" for c, n in meta["records_code"].items())
               if records else "")
    if "records_ranking_weights" in meta:
        made_by += "\n- ranking weights (α, β, γ) of the trials: " + ", ".join(
            f"{w} ({n})" for w, n in meta["records_ranking_weights"].items())
    if "records_pose_model" in meta:
        made_by += "\n- pose models of the trials (diffusion checkpoint id, or nn:index@id): " + ", ".join(
            f"{m} ({n})" for m, n in meta["records_pose_model"].items())
    header = (f"# {title}\n\n- command: `{meta['command']}`\n- wall time: {total / 60:.1f} min{resumed}\n"
              f"- machine: {meta['machine']}\n- code: {meta['code']}{made_by}\n"
              + ("- **quick slice** (`--quick`): a small part of the protocol, not the full experiment\n" if quick else "")
              + "\n")
    atomic_write_text(directory / REPORT_FILE, header + body_markdown)
    atomic_write_text(directory / SUMMARY_FILE, json.dumps({**meta, "title": title, **summary}, indent=2, sort_keys=True) + "\n")
    return directory / REPORT_FILE


def _earlier_wall_time(directory: Path) -> float:
    """Wall time of the earlier invocations of a resumed experiment (0 for a fresh one)."""
    try:
        return float(json.loads((directory / SUMMARY_FILE).read_text()).get("wall_time_s", 0.0))
    except (OSError, ValueError):
        return 0.0


def write_index(out: str | os.PathLike) -> Path:
    """`<out>/README.md`: one row per run (`evaluation.results_index`; for the repository's results/, docs/results.md too)."""
    from evaluation.results_index import write_index as write

    return write(Path(out))

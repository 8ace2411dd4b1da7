"""The final split's evaluation: `gd2p eval EXPERIMENT --split final`, the one path that may load its objects.

The final split (`shared/world/objects/final_split.py`) is measured once per release, with settings frozen
on val beforehand, and reported whether good or bad. So a final run:

1. refuses a dirty tree (`git status --porcelain --untracked-files=no`: any tracked file changed), so the
   commit it records is the code that ran;
2. checks the final objects against the committed manifest (a changed generator is refused, naming the object);
3. opens the final-split access (`final_split_access`) in this process and in every worker it spawns, and runs
   the trial protocol on the final objects with their own placement and world seeds
   (`push_protocol.FINAL_SEED_PREFIX`) into `<out>/<experiment>-<world>[-cameraN]-final[-tag]/`;
4. appends one line to `results/final/LOG.md` (date, commit, command, settings, summary path), whether the
   run finished or failed.

No other module opens the access (tests/test_final_split.py checks it).
"""
from __future__ import annotations

import datetime as dt
import subprocess
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

from shared.world.objects.final_split import (
    FinalSplitChangedError,
    final_split_access,
    load_final_split,
    manifest_sha256,
)

REPO_ROOT = Path(__file__).resolve().parents[1]
LOG_HEADER = ("# Final-split runs\n\nEvery `gd2p eval EXPERIMENT --split final` appends a line here, whether it finished "
              "or failed (evaluation/final_run.py). Final results are measured once per release, with settings frozen "
              "on val: see docs/evaluation.md#final-split.\n\n"
              "| date (UTC) | commit | command | settings | result |\n|---|---|---|---|---|\n")


class FinalRunError(RuntimeError):
    """A final run refused before it started (a dirty tree, no git, a changed final object)."""


def log_path(repo: Path | None = None) -> Path:
    return (repo or REPO_ROOT) / "results" / "final" / "LOG.md"


def _git(repo: Path, *args: str) -> str:
    try:
        done = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=60, check=True)
    except (OSError, subprocess.SubprocessError) as exc:
        raise FinalRunError(f"the final split runs from a git checkout (its commit is recorded): `git {' '.join(args)}` "
                            f"failed in {repo}: {exc}") from None
    return done.stdout


def clean_commit(repo: Path | None = None) -> str:
    """The commit HEAD, refusing a tree whose tracked files differ from it (FinalRunError naming them)."""
    repo = repo or REPO_ROOT
    changed = [line[3:] for line in _git(repo, "status", "--porcelain", "--untracked-files=no").splitlines() if line.strip()]
    if changed:
        shown = ", ".join(changed[:5]) + (f" and {len(changed) - 5} more" if len(changed) > 5 else "")
        raise FinalRunError(f"the final split runs from a clean tree only (the commit it records must be the code that "
                            f"ran); commit or stash: {shown}")
    return _git(repo, "rev-parse", "HEAD").strip()


def append_log(command: str, commit: str, settings: dict[str, Any], result: str, repo: Path | None = None,
               now: dt.datetime | None = None) -> Path:
    """Append one run's line to results/final/LOG.md (created with its header the first time)."""
    path = log_path(repo)
    path.parent.mkdir(parents=True, exist_ok=True)
    when = (now or dt.datetime.now(dt.timezone.utc)).strftime("%Y-%m-%d %H:%M")
    shown = ", ".join(f"{key}={value}" for key, value in settings.items())

    def cell(text: str) -> str:
        return text.replace("|", "\\|").replace("\n", " ")

    line = f"| {when} | {commit[:12]} | `{cell(command)}` | {cell(shown)} | {cell(result)} |\n"
    with path.open("a", encoding="utf-8") as log:
        if log.tell() == 0:
            log.write(LOG_HEADER)
        log.write(line)
    return path


_worker_access: list[AbstractContextManager[None]] = []  # a final run's worker holds its access here, for life


def open_access_for_life() -> None:
    """Open the final-split access for the rest of this process (a final run's worker). The open context is kept
    referenced: an unreferenced one is collected at once, and collecting it closes the access again."""
    access = final_split_access()
    access.__enter__()
    _worker_access.append(access)


def _init_final_worker(grasp_cache: str) -> None:
    """A final run's worker: the final-split access stays open for the worker's life, then the usual setup."""
    from evaluation.push_protocol import _init_worker

    open_access_for_life()
    _init_worker(grasp_cache)


def run_final(experiment: str, run: Callable[..., Path], out: Path, *, quick: bool, workers: int, command: str,
              options: dict[str, Any], repo: Path | None = None) -> Path:
    """Run `run` (a trial experiment's function) on the final split and log it; FinalRunError when refused."""
    commit = clean_commit(repo)
    settings = {"experiment": experiment, "quick": quick, "workers": workers,
                **{key: value for key, value in options.items() if value is not None}}
    with final_split_access():
        try:
            load_final_split()  # the objects are the frozen ones, or nothing runs
            settings["manifest"] = manifest_sha256()[:12]
            report = run(out, quick=quick, workers=workers, split="final", worker_init=_init_final_worker, **options)
        except BaseException as exc:  # reported whether good or bad: a failed or stopped run is logged too
            append_log(command, commit, settings, f"failed: {type(exc).__name__}: {str(exc)[:200]}", repo)
            if isinstance(exc, FinalSplitChangedError):
                raise FinalRunError(str(exc)) from None
            raise
    summary = report.parent / "summary.json"
    append_log(command, commit, settings, f"{_relative(summary, repo or REPO_ROOT)}", repo)
    return report


def _relative(path: Path, repo: Path) -> str:
    try:
        return str(path.resolve().relative_to(repo.resolve()))
    except ValueError:
        return str(path)

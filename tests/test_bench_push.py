"""bench/push.py --base: the ratios of two runs, the base's flags, a bad commit (no system is started)."""
from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType, SimpleNamespace
from typing import Any

import pytest

from conftest import load_bench

PUSH = Path(__file__).resolve().parent.parent / "bench" / "push.py"


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    return load_bench("push")


def run_json(to_plan: tuple[float, float], total_p50: float, objects: tuple[str, ...] = ("a",)) -> dict[str, Any]:
    """A made-up summary with the figures `merge` reads (as bench/push.py prints them)."""
    return {"to_plan_s": {"p50": to_plan[0], "p95": to_plan[1]}, "latency_s": {"p50": total_p50, "p95": 9.0},
            "requests": 2 * len(objects),
            "rows": [{"object": o, "direction_deg": d} for o in objects for d in (90.0, -90.0)]}


def test_merge_gives_base_over_current(bench: ModuleType) -> None:
    merged = bench.merge({"commit": "b", **run_json((3.0, 6.0), 5.0)}, {"commit": "c", **run_json((1.5, 4.0), 4.0)})
    assert merged["base"]["commit"] == "b" and merged["current"]["commit"] == "c"
    assert merged["speedup_p50"] == 2.0
    assert merged["speedup_p95"] == 1.5
    assert merged["speedup_end_to_end_p50"] == 1.25
    assert merged["same_requests"]


def test_common_requests_compare_only_what_both_served(bench: ModuleType) -> None:
    # The base pushed two objects (no --objects), the current one: the common ratio reads the rows of "a" only.
    def row(obj: str, direction: float, planning: float) -> dict[str, Any]:
        return {"object": obj, "direction_deg": direction, "stages_s": {"planning": planning, "execution": 9.0}}

    base = {**run_json((5.0, 6.0), 5.0), "rows": [row("a", 90.0, 2.0), row("a", -90.0, 4.0), row("b", 90.0, 9.0)]}
    current = {**run_json((1.0, 2.0), 4.0), "rows": [row("a", 90.0, 1.0), row("a", -90.0, 2.0)]}
    merged = bench.merge(base, current)
    assert not merged["same_requests"]
    assert merged["speedup_p50"] == 5.0
    assert merged["speedup_p50_common"] == 2.0  # medians 3.0 / 1.5, execution left out


def test_merge_without_figures_has_no_ratio(bench: ModuleType) -> None:
    # A run that served no request prints NaN percentiles: no ratio rather than NaN or a division by zero.
    merged = bench.merge(run_json((3.0, 6.0), 5.0, ("a", "b")), run_json((math.nan, math.nan), 0.0))
    assert merged["speedup_p50"] is None and merged["speedup_p95"] is None
    assert merged["speedup_end_to_end_p50"] is None
    assert not merged["same_requests"]


def test_comparison_table_names_both_commits(bench: ModuleType) -> None:
    merged = bench.merge({"commit": "b" * 40, **run_json((3.0, 6.0), 5.0)},
                         {"commit": "c" * 40, "dirty": True, **run_json((1.5, 4.0), 4.0)})
    table = bench.comparison_table({"dropped_flags": ["--objects 1"], **merged})
    assert "bbbbbbbbbb" in table and "cccccccccc-dirty" in table and "2.00x" in table
    assert "--objects 1" in table


def test_bad_commit_is_a_usage_error_before_any_worktree(bench: ModuleType, monkeypatch: pytest.MonkeyPatch,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    def forbidden(*_: object, **__: object) -> None:
        raise AssertionError("started although the commit is bad")

    monkeypatch.setattr(bench, "start_system", forbidden)
    monkeypatch.setattr(bench, "base_checkout", forbidden)
    worktrees = subprocess.run(["git", "worktree", "list"], cwd=PUSH.parent, capture_output=True, text=True).stdout
    with pytest.raises(SystemExit) as exited:
        bench.main(["--base", "no-such-commit-0000", "--json"])
    assert exited.value.code == 2
    assert "--base 'no-such-commit-0000' is not a commit" in capsys.readouterr().err
    assert subprocess.run(["git", "worktree", "list"], cwd=PUSH.parent, capture_output=True,
                          text=True).stdout == worktrees


def old_parser() -> argparse.ArgumentParser:
    """A base's bench without --objects, --view and --base; its description mentions a flag it lacks."""
    parser = argparse.ArgumentParser(description="python bench/push.py --objects 1 (a later bench)",
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    parser.add_argument("--k", type=int, default=200)
    parser.add_argument("--method", choices=("auto", "gd2p", "fixed"), default="auto")
    parser.add_argument("--sampler", choices=("ddpm", "ddim"), default="ddpm")
    parser.add_argument("--no-critic", dest="critic", action="store_false",
                        help="a long help text that argparse wraps onto the next line, naming --objects as well")
    parser.add_argument("--record-dir", default="/tmp/x")
    parser.add_argument("--validators", type=int, default=None)
    return parser


def test_flags_the_base_does_not_know_are_dropped(bench: ModuleType) -> None:
    known = bench.help_flags(old_parser().format_help())
    assert "--objects" not in known and {"--k", "--no-critic", "--validators", "--help"} <= known
    args = bench.build_parser().parse_args(["--k", "8", "--objects", "1", "--validators", "1", "--no-critic"])
    argv, dropped = bench.filter_flags(bench.shared_flags(args), known)
    assert dropped == ["--objects 1"]
    assert argv[:7] == ["--json", "--k", "8", "--method", "auto", "--sampler", "ddpm"]
    assert {"--validators", "1", "--no-critic"} <= set(argv) and "--objects" not in argv


def test_this_bench_accepts_every_flag_it_passes(bench: ModuleType) -> None:
    # Run against its own commit, nothing may be dropped.
    args = bench.build_parser().parse_args(["--validators", "1", "--no-critic", "--no-prescreen", "--view"])
    _, dropped = bench.filter_flags(bench.shared_flags(args), bench.help_flags(bench.build_parser().format_help()))
    assert dropped == []


def test_the_memory_figure_counts_every_service_process_while_it_runs(bench: ModuleType) -> None:
    """A service holding 300 MiB shows in the peak, whatever this process holds, and is still counted after it
    exits (a peak, not the last reading); PSS never exceeds RSS."""
    hold = "import time; x = b'\\x01' * (300 * 2**20); print('ready', flush=True); time.sleep(30)"
    holder = subprocess.Popen([sys.executable, "-c", hold], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "ready"
        launcher = SimpleNamespace(children=lambda: [SimpleNamespace(process=holder)])
        own = bench._smaps_rollup(os.getpid())
        assert own is not None
        memory = bench.MemoryPeak(launcher, period_s=0.05)
        time.sleep(0.5)
    finally:
        holder.kill()
        holder.wait()
    time.sleep(0.2)
    figures = memory.summary(validators=2)
    assert figures["processes"] == 2 and figures["validators"] == 2
    assert figures["peak_rss_gib"] * 2**20 >= own[0] + 300 * 2**10
    assert figures["peak_pss_gib"] <= figures["peak_rss_gib"]


def test_the_cpu_figure_counts_what_each_service_process_spends(bench: ModuleType) -> None:
    """A validator burning 0.3 s of CPU shows as its service's seconds between two readings; an idle one adds ~0."""
    burn = ("import time; print('ready', flush=True); input(); t = time.process_time(); "
            "exec('while time.process_time() - t < 0.3: pass'); print('done', flush=True); time.sleep(30)")
    busy = subprocess.Popen([sys.executable, "-c", burn], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    idle = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        assert busy.stdout is not None and busy.stdin is not None and busy.stdout.readline().strip() == "ready"
        launcher = SimpleNamespace(children=lambda: [SimpleNamespace(service="validator", process=busy),
                                                     SimpleNamespace(service="sampler", process=idle)])
        before = bench.service_cpu_s(launcher)
        busy.stdin.write("\n")
        busy.stdin.flush()
        assert busy.stdout.readline().strip() == "done"
        used = bench.cpu_used(before, bench.service_cpu_s(launcher))
    finally:
        for process in (busy, idle):
            process.kill()
            process.wait()
    assert 0.25 <= used["validator"] <= 1.0
    assert used["sampler"] < 0.05
    assert used["total"] == pytest.approx(sum(v for k, v in used.items() if k != "total"), abs=0.002)

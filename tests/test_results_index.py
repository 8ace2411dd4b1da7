"""The results index is generated and cannot go stale: results/README.md and docs/results.md are what
`python -m evaluation.results_index` writes from the runs in results/, docs/results.md stays short, and every run
either links exists."""

from __future__ import annotations

import json
import re
from pathlib import Path

from evaluation.results_index import (
    COMMAND,
    DOCS_MAX_LINES,
    DOCS_RESULTS,
    RESULTS,
    describe,
    is_run,
    newest,
    read_runs,
    render_docs,
    render_index,
)

LINK = re.compile(r"\]\(([^)#]+)\)")


def test_the_committed_index_and_docs_are_what_the_generator_writes():
    runs = read_runs(RESULTS)
    assert (RESULTS / "README.md").read_text() == render_index(runs), f"results/README.md is stale: run `{COMMAND}`"
    assert DOCS_RESULTS.read_text() == render_docs(runs), f"docs/results.md is stale: run `{COMMAND}`"


def test_the_results_page_is_short_and_says_it_is_generated():
    text = DOCS_RESULTS.read_text()
    assert len(text.splitlines()) <= DOCS_MAX_LINES
    assert COMMAND in text.split("\n\n")[1] and COMMAND in (RESULTS / "README.md").read_text().split("\n\n")[1]


def test_every_run_linked_exists_and_every_kept_run_is_listed():
    index = (RESULTS / "README.md").read_text()
    for page in (RESULTS / "README.md", DOCS_RESULTS):
        for target in LINK.findall(page.read_text()):
            assert (page.parent / target).exists(), f"{page.name} links {target}, which is not in the tree"
    for run in filter(is_run, RESULTS.iterdir()):
        assert f"[{run.name}]({run.name}/" in index


def test_a_run_is_grouped_with_the_other_runs_of_its_experiment_and_the_newest_is_kept(tmp_path):
    def run(name: str, date: str, settings: dict, **summary) -> Path:
        (tmp_path / name).mkdir()
        (tmp_path / name / "settings.json").write_text(json.dumps(settings))
        (tmp_path / name / "summary.json").write_text(json.dumps({"date": date, "code": "abc1234", **summary}))
        return tmp_path / name

    methods = {"gd2p": {"success_rate": 0.9, "trials": 42, "interval_95": {"value": 0.9, "low": 0.8, "high": 1.0}}}
    protocol = {"hand": "allegro", "cameras": 3, "objects": ["a", "b"], "directions_deg": [0.0, 90.0, 180.0]}
    old = run(
        "methods-real-camera3-v1",
        "2026-12-01T00:00:00Z",
        protocol,
        methods=methods,
        command="gd2p eval methods --cameras 3 --trials 7 --methods gd2p --tag v1 --out /somewhere --workers 2",
    )
    new = run("methods-real-camera3-v2", "2026-12-02T00:00:00Z", protocol, methods=methods)
    val = run("methods-real-camera3-val-v3", "2026-12-03T00:00:00Z", protocol, methods=methods)
    closed = run(
        "multistep-real-v2-ahead-closed",
        "2026-12-01T00:00:00Z",
        {"closed_loop": True},
        runs=18,
        success_rate=0.5,
        interval_95={"value": 0.5, "low": 0.2, "high": 0.8},
    )
    opened = run("multistep-real-v2-ahead", "2026-12-01T00:00:00Z", {}, runs=18, success_rate=0.5)

    described = {p.name: describe(p) for p in (old, new, val, closed, opened)}
    assert described[old.name].key == described[new.name].key != described[val.name].key  # a tag is another run
    assert described[closed.name].key != described[opened.name].key  # closed loop is another experiment
    assert described[old.name].command == "gd2p eval methods --cameras 3 --trials 7 --methods gd2p --tag v1"
    assert "7 per object and direction" in described[old.name].seeds
    kept = {r.name for r in newest(read_runs(tmp_path)).values()}
    assert kept == {new.name, val.name, closed.name, opened.name}
    index = render_index(read_runs(tmp_path))
    assert "| gd2p: 90.0% [80.0%, 100.0%] |" in index and "no interval recorded" in index  # the open-loop run


def test_a_mujoco_run_a_task_run_and_a_suite_are_told_apart(tmp_path):
    def run(name: str, **summary) -> Path:
        (tmp_path / name).mkdir()
        (tmp_path / name / "settings.json").write_text(json.dumps({"hand": "allegro", "cameras": 3}))
        (tmp_path / name / "summary.json").write_text(json.dumps({"date": "2026-12-07T00:00:00Z", **summary}))
        return tmp_path / name

    interval = {"value": 0.8, "low": 0.7, "high": 0.9}
    methods = {"gd2p-closed-critic-p24": {"success_rate": 0.8, "trials": 30, "interval_95": interval}}
    paper = describe(run("closed-loop-mujoco-camera3-levelled", methods=methods))
    pose = describe(run("closed-loop-mujoco-camera3-pose-levelled", methods=methods))
    suite = describe(run("suite-mujoco-camera3-levelled", methods=["gd2p-closed-critic-p24"],
                         suite={"gd2p-closed-critic-p24": {"trials": 60, "interval_95": interval}}))
    assert (paper.world, paper.seen, paper.tag, paper.variant) == ("mujoco", "mujoco, 3 cameras", "levelled", "")
    assert pose.variant == "task pose" and pose.key != paper.key and pose.tag == "levelled"
    assert suite.experiment == "suite" and [(r.label, r.count) for r in suite.rows] == [("gd2p-closed-critic-p24", 60)]


def test_the_results_page_leads_with_the_final_split(tmp_path):
    """The held-out figures come first on docs/results.md, marked as the final split; the development run after."""
    interval = {"value": 0.5, "low": 0.4, "high": 0.6}
    for name in ("suite-real-camera3-levelled", "suite-real-camera3-final"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "settings.json").write_text(json.dumps({"hand": "allegro", "cameras": 3}))
        (tmp_path / name / "summary.json").write_text(json.dumps({
            "date": "2026-12-07T00:00:00Z", "title": "Suite", "methods": ["gd2p-closed-critic-p24"],
            "suite": {"gd2p-closed-critic-p24": {"trials": 384, "interval_95": interval}}}))
    page = render_docs(read_runs(tmp_path))
    headings = [line for line in page.splitlines() if line.startswith("## ")]
    assert headings == ["## Suite — final split", "## Suite"]
    assert "final split (held out, measured once per release" in page


def headings_of_closed_loop_runs(tmp_path: Path, runs: tuple[tuple[str, str, tuple[str, ...]], ...]) -> tuple[list[str], str]:
    """The results page's headings and the index for closed-loop runs (name, date, methods) written to `tmp_path`."""
    one = {"success_rate": 0.9, "trials": 84, "interval_95": {"value": 0.9, "low": 0.8, "high": 1.0}}
    for name, date, methods in runs:
        (tmp_path / name).mkdir()
        (tmp_path / name / "settings.json").write_text(json.dumps({"hand": "allegro", "cameras": 3}))
        (tmp_path / name / "summary.json").write_text(json.dumps(
            {"date": date, "title": name, "methods": {m: one for m in methods}}))
    read = read_runs(tmp_path)
    return [line for line in render_docs(read).splitlines() if line.startswith("## ")], render_index(read)


def test_a_newer_run_of_one_method_does_not_stand_in_for_the_run_that_compared_them(tmp_path):
    """One side of an A/B (the default alone, another setting) is newer than the run of every method, yet the
    results page keeps showing the comparison; the index lists both."""
    headings, index = headings_of_closed_loop_runs(tmp_path, (
        ("closed-loop-real-camera3-levelled", "2026-12-06T00:00:00Z", ("a", "b")),
        ("closed-loop-real-camera3-hold-on", "2026-12-07T00:00:00Z", ("a",))))
    assert headings == ["## closed-loop-real-camera3-levelled"]
    assert "closed-loop-real-camera3-hold-on" in index


def test_a_newer_ab_of_the_default_against_an_ablation_does_not_stand_in_for_the_comparison(tmp_path):
    """The default against a tuning candidate of evaluation/methods.yaml (the reused-paths ablation) on the
    development objects is newer than the run comparing the methods; the results page keeps the comparison."""
    headings, index = headings_of_closed_loop_runs(tmp_path, (
        ("closed-loop-real-camera3-levelled", "2026-12-06T00:00:00Z", ("gd2p-closed-critic-p24", "fixed-corrected")),
        ("closed-loop-real-camera3-reuse", "2026-12-08T00:00:00Z", ("gd2p-closed-critic-p24", "gd2p-closed-critic-rrt"))))
    assert headings == ["## closed-loop-real-camera3-levelled"]
    assert "closed-loop-real-camera3-reuse" in index

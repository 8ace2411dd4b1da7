"""End-to-end push requests: latency by stage and success over a fixed set of objects and directions.

    python bench/push.py --json      # last line: one JSON object

The system runs as `gd2p up` brings it up (`deploy.launcher`: an embedded router and one process
per service, one validator per core unless `--validators`); each request goes through the push
client exactly as `gd2p push` sends it, one at a time (the next once the previous storyboard is
rendered). Start-up is not timed. K = 200 candidate poses from the diffusion sampler
(method "gd2p"; `--sampler ddim --no-prescreen` for the fast path: the success critic's order, no prescreen) when an
Allegro checkpoint is at the default
path, else the fixed spatula pose (method "fixed", one candidate) — the JSON says which. Stages
(from the response's timings): sampling, ik (batched IK + collision and push-line screen),
prescreen (floating-hand pushes of the best-aligned feasible poses), planning (RRTConnect +
Cartesian segments; the validators roll finished plans out meanwhile), rollouts (the wait for the
last arm rollouts after planning), execution (the simulated robot bridge, at full physics speed);
"total" is the client's wall time per request, `to_plan_s` everything before execution.

`--view`: the live view's cost (its budget: at most 5 % of a push's end-to-end time). Each request runs twice,
without and with the view attached (`cli.view.ViewBus` + `visualisation.live.LiveView` in this process, with
a headless Chromium watching it when `--browser`), in alternating order; the JSON gives both medians and
their ratio, and how the view keeps up with a tracker at 20 Hz (`view_tracking`: ObjectTracks at 20 Hz and
robot states at 500 Hz fed for 5 s; frames drawn per second and the lag from a pose's stamp to its drawing).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from client.push_client import PushFailed, push
from deploy.launcher import Launcher, free_loopback_endpoint
from shared.bus import BusConfig
from shared.contracts.messages import ObjectRef, PlannerOptions, PushRequest

OBJECTS = ("proc-box-013", "proc-box-000", "proc-cylinder-000")  # test split
DIRECTIONS_DEG = (90.0, -90.0)  # sideways both ways from the default spot 0.55 m in front of the robot
STAGES = ("sampling", "ik", "prescreen", "planning", "rollouts", "execution")


def start_system(record_dir: str, validators: int | None) -> tuple[Launcher, BusConfig]:
    """The system as `gd2p up` brings it up (router + one process per service); (launcher, client config)."""
    launcher = Launcher(validators=validators, listen=free_loopback_endpoint(), record_dir=record_dir)
    launcher.start()
    try:
        launcher.wait_ready(120.0)
    except BaseException:
        launcher.stop()
        raise
    return launcher, BusConfig(mode="client", connect=[launcher.endpoint], connect_timeout_ms=5000)


def wait_for_storyboard(recording_path: str | None, timeout_s: float = 60.0) -> None:
    """Until the planner has rendered the request's storyboard (after answering, on its own thread).

    Each request is then timed alone: back to back, the previous storyboard's rendering shares the
    planner's CPU and adds about 0.5 s to the next request's IK and planning stages.
    """
    if recording_path is None:
        return
    png = Path(recording_path).with_suffix(".png")
    deadline = time.monotonic() + timeout_s
    while not png.exists() and time.monotonic() < deadline:
        time.sleep(0.1)


def percentile(values: Sequence[float], q: float) -> float:
    return round(float(np.percentile(values, q)), 3) if values else float("nan")


class ViewBench:
    """The live view attached to the system or not (its subscriptions declared or undeclared), in this process."""

    def __init__(self, cfg: BusConfig, browser: bool):
        from cli.view import ViewBus
        from shared.bus import open_session
        from visualisation.live import LiveView

        self.session = open_session(cfg)
        self.view = LiveView(port=0)
        self._make_bus = lambda: ViewBus(self.session, self.view)
        self.bus: Any = None  # the view's bus adapter while attached (cli.view.ViewBus)
        self.driver = None
        if browser:
            self.driver = _browser()
            self.driver.get(self.view.url)

    def attach(self, on: bool) -> None:
        if on and self.bus is None:
            self.bus = self._make_bus()
        elif not on and self.bus is not None:
            self.bus.close()
            self.bus = None

    def summary(self, rows: list[dict]) -> dict:
        self.attach(False)
        pairs: dict[tuple[str, float], dict[bool, float]] = {}
        for r in rows:
            if "stages_s" in r:
                pairs.setdefault((r["object"], r["direction_deg"]), {})[r["view"]] = r["total_s"]
        both = [p for p in pairs.values() if len(p) == 2]
        off = statistics.median([p[False] for p in both]) if both else None
        on = statistics.median([p[True] for p in both]) if both else None
        return {"pairs": len(both), "browser": self.driver is not None, "total_s_without": off, "total_s_with": on,
                "ratio_median": round(statistics.median([p[True] / p[False] for p in both]), 4) if both else None,
                "ratio_of_sums": round(sum(p[True] for p in both) / sum(p[False] for p in both), 4) if both else None,
                "target_ratio": 1.05, "view_counts": self.view.counts(), "view_tracking": view_tracking(self.view)}

    def close(self) -> None:
        if self.driver is not None:
            self.driver.quit()
        self.attach(False)
        self.view.close()
        self.session.close()


def view_tracking(view, seconds: float = 5.0, track_hz: float = 20.0, state_hz: float = 500.0) -> dict:
    """Feed `view` ObjectTracks at `track_hz` and ExecutionStates at `state_hz` for `seconds`; how it kept up."""
    from shared.contracts.messages import ExecutionState, ObjectPose, ObjectTrack

    view.reset_track_stats()
    names = [f"panda_joint{i}" for i in range(1, 8)]
    started = time.monotonic()
    next_track = 0.0
    sent = 0
    while (t := time.monotonic() - started) < seconds:
        q = np.full(7, 0.1 * np.sin(t))
        view.show_state(ExecutionState(stamp=time.time(), joint_names=names, positions=q, velocities=np.zeros(7),
                                       status="executing"))
        if t >= next_track:
            view.show_track(ObjectTrack(stamp=time.time(), pose=ObjectPose(position=(0.55, 0.1 * t / seconds, 0.04)),
                                        source="bench"))
            sent += 1
            next_track += 1.0 / track_hz
        time.sleep(1.0 / state_hz)
    time.sleep(0.2)
    stats = view.track_stats()
    return {"tracks_sent": sent, "track_hz": track_hz, "state_hz": state_hz,
            **{k: round(v, 4) for k, v in stats.items()}}


def _browser():
    import shutil
    import tempfile

    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium") or "chromium"
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run",
                 f"--user-data-dir={tempfile.mkdtemp(prefix='gd2p-bench-chromium-')}"):
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(shutil.which("chromedriver") or "/usr/bin/chromedriver"), options=options)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    parser.add_argument("--k", type=int, default=200)
    parser.add_argument("--method", choices=("auto", "gd2p", "fixed"), default="auto")
    parser.add_argument("--sampler", choices=("ddpm", "ddim"), default="ddpm",
                        help="diffusion sampler of method gd2p (DDIM-10: the fast path)")
    parser.add_argument("--no-critic", dest="critic", action="store_false",
                        help="PlannerOptions.critic off: L_dir's order instead of the success critic's (the default)")
    parser.add_argument("--no-prescreen", dest="prescreen", action="store_false",
                        help="PlannerOptions.prescreen off: no floating-hand pushes before planning (with DDIM: the fast path)")
    parser.add_argument("--record-dir", default="/tmp/gd2p-bench-push")
    parser.add_argument("--validators", type=int, default=None,
                        help="validator processes (default: one per core, as `gd2p up`)")
    parser.add_argument("--view", action="store_true", help="each request without and with the live view attached")
    parser.add_argument("--browser", action="store_true", help="with --view: a headless Chromium watches the view")
    parser.add_argument("--objects", type=int, default=len(OBJECTS), help="the first N objects only (a busy machine)")
    args = parser.parse_args(argv)
    from shared.sampling.checkpoint import default_checkpoint_path

    method = args.method
    if method == "auto":
        method = "gd2p" if default_checkpoint_path("allegro").is_file() else "fixed"
    launcher, cfg = start_system(args.record_dir, args.validators)
    rows: list[dict[str, Any]] = []
    watch = ViewBench(cfg, args.browser) if args.view else None
    try:
        options = PlannerOptions(k=args.k, method=method, sampler=args.sampler, critic=args.critic,
                                 prescreen=args.prescreen)
        if watch is not None:  # a warm-up request, not timed: the first push pays one-time loads on both sides
            try:
                warm = push(PushRequest(object=ObjectRef(library_id=OBJECTS[0]), direction_deg=DIRECTIONS_DEG[0],
                                        options=options), cfg, timeout_s=300.0)
                wait_for_storyboard(warm.recording_path)
            except PushFailed:
                pass
        for i, (object_id, direction, viewed) in enumerate(
                (o, d, v) for o in OBJECTS[:args.objects] for d in DIRECTIONS_DEG
                for v in ((False, True) if watch is not None else (False,))):
            if watch is not None:
                viewed = viewed != bool((i // 2) % 2)  # alternate which of the pair runs first
                watch.attach(viewed)
            request = PushRequest(object=ObjectRef(library_id=object_id), direction_deg=direction, options=options)
            started = time.perf_counter()
            try:
                response = push(request, cfg, timeout_s=300.0)
                row = {"object": object_id, "direction_deg": direction, "success": response.success,
                       "position_error_m": round(response.result.position_error_m, 4),
                       "rotation_deg": round(response.result.rotation_deg, 1),
                       "stages_s": {k: round(v, 3) for k, v in response.timings_s.items()}}
            except PushFailed as exc:
                row = {"object": object_id, "direction_deg": direction, "success": False, "error": exc.code,
                       "message": exc.message[:200]}
            row["total_s"] = round(time.perf_counter() - started, 3)
            if watch is not None:
                row["view"] = viewed
            rows.append(row)
            if "stages_s" in row:
                wait_for_storyboard(response.recording_path)
            if not args.json:
                print(json.dumps(row))
        view_summary = watch.summary(rows) if watch is not None else None
    finally:
        if watch is not None:
            watch.close()
        launcher.stop()
    if view_summary is not None:
        rows = [r for r in rows if not r["view"]] + [r for r in rows if r["view"]]
    served = [r for r in rows if "stages_s" in r and not r.get("view")]
    totals = [r["total_s"] for r in served]
    to_plan = [sum(r["stages_s"].get(s, 0.0) for s in STAGES if s != "execution") for r in served]
    from evaluation.report import code_version, machine

    summary = {
        "machine": machine(), "date": time.strftime("%Y-%m-%d"), "code": code_version(),
        "method": method, "sampler": args.sampler if method == "gd2p" else None, "critic": args.critic, "prescreen": args.prescreen, "validators": args.validators or os.cpu_count(), "k": args.k if method == "gd2p" else 1, "requests": len(rows),
        "success": sum(r["success"] for r in rows), "success_rate": round(sum(r["success"] for r in rows) / len(rows), 3),
        "infeasible": sum(r.get("error") == "infeasible" for r in rows),
        "latency_s": {"p50": percentile(totals, 50), "p95": percentile(totals, 95), "target_p50": 3.0},
        # Until the plan is chosen (every stage but execution, which takes the robot's own time on hardware).
        "to_plan_s": {"p50": percentile(to_plan, 50), "p95": percentile(to_plan, 95), "target_p50": 1.5,
                      "target_p95": 3.0},
        "stages_s": {s: {"p50": percentile([r["stages_s"].get(s, 0.0) for r in served], 50),
                         "p95": percentile([r["stages_s"].get(s, 0.0) for r in served], 95)} for s in STAGES},
        "median_total_in_planner_s": round(statistics.median([r["stages_s"]["total"] for r in served]), 3) if served else None,
        "rows": rows,
    }
    if view_summary is not None:
        summary["view"] = view_summary
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())

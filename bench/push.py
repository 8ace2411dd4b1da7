"""End-to-end push requests: latency by stage and success over a fixed set of objects and directions.

    python bench/push.py --json      # last line: one JSON object
    python bench/push.py --base 76ddcd8 --json      # that commit's planner, then this one's: both and their ratio

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

`--base COMMIT`: the machines these run on differ in speed by up to 1.7x, so a speed-up is measured within one run.
A clean checkout of COMMIT in a temporary git worktree (removed afterwards, also on failure or Ctrl-C) runs its own
bench/push.py first, as a subprocess with the same Python; then this code runs in this process exactly as without
`--base`. The base gets the flags it understands (read from its `--help`; the JSON lists the ones it does not
know in `dropped_flags`) and `--record-dir` with `-base` appended. The JSON holds both runs (`base`, `current`:
each with its commit; `dirty` when this tree has uncommitted changes) and the ratios base / current:
`speedup_p50` and `speedup_p95` of `to_plan_s`, `speedup_end_to_end_p50` of `latency_s` (the client's total);
`same_requests` false when the runs pushed different requests (a base without `--objects` pushes all), and
`speedup_p50_common` the to-plan p50 ratio over the requests both served.
Without `--json` a short table compares them.

`memory`: the whole system's peak while the bench runs (`MemoryPeak`: the service processes and this one, which
embeds the router), as resident set (RSS, an upper bound: shared libraries count in every process) and proportional
set (PSS, what the machine holds); issue 50's target is 6 GiB with 2 validators.

`cpu_s_per_request`: the CPU seconds a request costs each service (the median over requests; each row's `cpu_s`),
read from /proc before and after it: with every core busy, the sum over the services that work before the robot
moves (the validators' physics, the sampler, the planner's share) divided by the cores is the least time to a plan
that this much work allows. The planner's and the robot bridge's figures include the execution.
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import json
import math
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import IO, Any

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


class MemoryPeak:
    """The system's peak memory while the bench runs: every 0.5 s, the sum over this process (the embedded router
    and the client) and every service process of their resident set (RSS: shared libraries counted in each
    process, an upper bound) and of their proportional set (PSS: each shared page split among its users, what the
    machine actually holds), from /proc/PID/smaps_rollup (Linux)."""

    def __init__(self, launcher: Launcher, period_s: float = 0.5) -> None:
        self._launcher = launcher
        self._period_s = period_s
        self._stop = threading.Event()
        self.peak_rss_kib = self.peak_pss_kib = 0
        self.processes = 0
        self._thread = threading.Thread(target=self._run, name="memory-peak", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            pids = [os.getpid(), *(c.process.pid for c in self._launcher.children())]
            sizes = [s for s in map(_smaps_rollup, pids) if s is not None]
            self.processes = max(self.processes, len(sizes))
            self.peak_rss_kib = max(self.peak_rss_kib, sum(rss for rss, _ in sizes))
            self.peak_pss_kib = max(self.peak_pss_kib, sum(pss for _, pss in sizes))

    def summary(self, validators: int) -> dict[str, Any]:
        self._stop.set()
        self._thread.join()
        return {"peak_rss_gib": round(self.peak_rss_kib / 2**20, 2), "peak_pss_gib": round(self.peak_pss_kib / 2**20, 2),
                "processes": self.processes, "validators": validators, "target_gib": 6.0}


def service_cpu_s(launcher: Launcher) -> dict[str, float]:
    """CPU seconds (user + system) each service has used so far, summed over its processes, and "bench" for this
    process (the embedded router and the client), from /proc/PID/stat (Linux; a process gone counts 0)."""
    tick = os.sysconf("SC_CLK_TCK")
    used: dict[str, float] = {"bench": sum(os.times()[:2])}
    for child in launcher.children():
        used[child.service] = used.get(child.service, 0.0) + _cpu_ticks(child.process.pid) / tick
    return used


def _cpu_ticks(pid: int) -> int:
    try:  # the fields after the command's ")" (which may hold spaces): utime and stime are the 12th and 13th
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return 0
    return int(fields[11]) + int(fields[12])


def cpu_used(before: dict[str, float], after: dict[str, float]) -> dict[str, float]:
    """CPU seconds per service between two `service_cpu_s` readings, and their "total"."""
    used = {name: round(after[name] - before.get(name, 0.0), 3) for name in after}
    return used | {"total": round(sum(used.values()), 3)}


def _smaps_rollup(pid: int) -> tuple[int, int] | None:
    """(RSS, PSS) of a process in KiB; None if it is gone or the kernel has no smaps_rollup."""
    try:
        text = Path(f"/proc/{pid}/smaps_rollup").read_text()
    except OSError:
        return None
    fields = dict(line.split(":", 1) for line in text.splitlines() if line.startswith(("Rss:", "Pss:")))
    return int(fields["Rss"].split()[0]), int(fields["Pss"].split()[0])


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


def build_parser() -> argparse.ArgumentParser:
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
    parser.add_argument("--base", metavar="COMMIT",
                        help="first run COMMIT's own bench/push.py (a temporary worktree), then this code; "
                             "the JSON holds both and their ratio (speedup_p50)")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.base is None:
        print(json.dumps(run(args)))
        return 0
    # Resolved before anything starts: a typo costs no worktree and no system start-up.
    base_commit = resolve_commit(args.base)
    if base_commit is None:
        parser.error(f"--base {args.base!r} is not a commit of the repository at {REPO}")
    try:
        result = compare(args, base_commit)
    except BaseBenchFailed as exc:
        print(f"bench/push.py: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(result) if args.json else comparison_table(result))
    return 0


def run(args: argparse.Namespace) -> dict[str, Any]:
    """This code's bench: the system started, each request pushed and timed; the summary (printed as JSON)."""
    from shared.sampling.checkpoint import default_checkpoint_path

    method = args.method
    if method == "auto":
        method = "gd2p" if default_checkpoint_path("allegro").is_file() else "fixed"
    launcher, cfg = start_system(args.record_dir, args.validators)
    memory = MemoryPeak(launcher)
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
            cpu_before = service_cpu_s(launcher)
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
            row["cpu_s"] = cpu_used(cpu_before, service_cpu_s(launcher))
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
        memory_summary = memory.summary(args.validators or os.cpu_count() or 1)
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
        # CPU seconds per request, by service (median over requests; execution and rendering the storyboard
        # included): the work a request asks of the machine, whichever core runs it.
        "cpu_s_per_request": {name: round(statistics.median([r["cpu_s"][name] for r in served]), 3)
                              for name in (served[0]["cpu_s"] if served else {})},
        "median_total_in_planner_s": round(statistics.median([r["stages_s"]["total"] for r in served]), 3) if served else None,
        "memory": memory_summary,
        "rows": rows,
    }
    if view_summary is not None:
        summary["view"] = view_summary
    return summary


# --base: the base commit's bench, then this one, in one run.

REPO = Path(__file__).resolve().parents[1]
BASE_STOP_S = 60.0  # after Ctrl-C, how long the base's bench gets to stop its system before it is killed


class BaseBenchFailed(RuntimeError):
    """The base commit's bench/push.py could not run, or printed no JSON; the message says why."""


def git(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=False)


def resolve_commit(ref: str) -> str | None:
    """The full hash of `ref` when it names a commit, else None (`--quiet`: no git message to parse)."""
    done = git("rev-parse", "--verify", "--quiet", f"{ref}^{{commit}}")
    return done.stdout.strip() if done.returncode == 0 else None


def current_commit() -> dict[str, Any]:
    """HEAD, and whether tracked code differs from it (results/ excluded, as `evaluation.report.code_version`)."""
    changed = git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)results").stdout.strip()
    return {"commit": git("rev-parse", "HEAD").stdout.strip(), "dirty": bool(changed)}


def shared_flags(args: argparse.Namespace) -> list[list[str]]:
    """The run's settings as flags for the base's bench, each with its values; explicit even when at their
    defaults, since the base's defaults may differ from this code's."""
    flags = [["--json"], ["--k", str(args.k)], ["--method", args.method], ["--sampler", args.sampler],
             ["--objects", str(args.objects)], ["--record-dir", args.record_dir.rstrip("/") + "-base"]]
    if args.validators is not None:
        flags.append(["--validators", str(args.validators)])
    flags += [[flag] for flag, on in (("--no-critic", not args.critic), ("--no-prescreen", not args.prescreen),
                                      ("--view", args.view), ("--browser", args.browser)) if on]
    return flags


def help_flags(help_text: str) -> set[str]:
    """The long options an argparse `--help` lists.

    Only option lines of its options section count (two spaces, then a dash): the description above it and
    the wrapped help texts may mention flags of other commands.
    """
    lines = help_text.splitlines()
    heads = [i for i, line in enumerate(lines) if line.rstrip() in ("options:", "optional arguments:")]
    flags: set[str] = set()
    for line in lines[heads[-1] + 1:] if heads else []:
        if line.startswith("  -"):
            invocation = line.strip().split("  ")[0]  # the help text follows after two or more spaces
            flags.update(word.rstrip(",") for word in invocation.split() if word.startswith("--"))
    return flags


def filter_flags(flags: list[list[str]], known: set[str]) -> tuple[list[str], list[str]]:
    """(argv of the flags `known` accepts, the others as "--flag value" for the JSON)."""
    argv = [word for flag in flags if flag[0] in known for word in flag]
    dropped = [" ".join(flag) for flag in flags if flag[0] not in known]
    return argv, dropped


@contextlib.contextmanager
def base_checkout(commit: str) -> Iterator[Path]:
    """A clean checkout of `commit` in a temporary worktree, removed on the way out however it is left."""
    parent = Path(tempfile.mkdtemp(prefix="gd2p-bench-base-"))
    checkout = parent / "checkout"
    try:
        added = git("worktree", "add", "--detach", str(checkout), commit)
        if added.returncode != 0:
            raise BaseBenchFailed(f"git worktree add {commit[:12]} failed: {added.stderr.strip()}")
        yield checkout
    finally:
        git("worktree", "remove", "--force", str(checkout))
        shutil.rmtree(parent, ignore_errors=True)
        git("worktree", "prune")  # forgets the worktree if its removal failed half way


def base_environment(checkout: Path) -> dict[str, str]:
    # The venv has this repository installed in editable mode: PYTHONPATH puts the base's packages first.
    return {**os.environ, "PYTHONPATH": str(checkout)}


def base_help(checkout: Path) -> str:
    """The base bench's `--help`; importing it also proves the base's code loads in this Python."""
    script = checkout / "bench" / "push.py"
    if not script.is_file():
        raise BaseBenchFailed("the base commit has no bench/push.py")
    done = subprocess.run([sys.executable, str(script), "--help"], cwd=checkout, env=base_environment(checkout),
                          capture_output=True, text=True, check=False, timeout=300)
    if done.returncode != 0:
        raise BaseBenchFailed(f"the base's bench/push.py cannot run in this Python ({sys.executable}): "
                              f"--help exited {done.returncode}:\n{_tail(done.stderr or done.stdout)}")
    return done.stdout


def run_base(checkout: Path, argv: list[str]) -> dict[str, Any]:
    """Run the base's bench with `argv` to its end; its JSON (its last stdout line).

    Its stderr is passed through as it comes (a full run takes minutes) and its end kept for the error.
    """
    with tempfile.TemporaryFile("w+") as out:
        proc = subprocess.Popen([sys.executable, str(checkout / "bench" / "push.py"), *argv], cwd=checkout,
                                env=base_environment(checkout), stdout=out, stderr=subprocess.PIPE, text=True,
                                errors="replace")
        assert proc.stderr is not None
        tail: collections.deque[str] = collections.deque(maxlen=20)
        tee = threading.Thread(target=_tee, args=(proc.stderr, tail), daemon=True)
        tee.start()
        try:
            code = proc.wait()
        finally:
            _stop(proc)
        tee.join(5.0)
        out.seek(0)
        lines = out.read().strip().splitlines()
    if code != 0 or not lines:
        raise BaseBenchFailed(f"the base's bench/push.py exited {code}:\n{''.join(tail).rstrip()}")
    try:
        return dict(json.loads(lines[-1]))
    except ValueError as exc:
        raise BaseBenchFailed(f"the base's bench/push.py printed no JSON last: {lines[-1][:200]!r}") from exc


def _tee(stream: IO[str], tail: collections.deque[str]) -> None:
    # Drained to its end on a thread, also after Ctrl-C: a full pipe would block the base's clean stop.
    for line in stream:
        sys.stderr.write(line)
        tail.append(line)


def _stop(proc: subprocess.Popen[str]) -> None:
    """Until the base's bench has ended: on Ctrl-C it got the SIGINT too and stops its system itself;
    a SIGINT of its own when only this process was interrupted; killed when it hangs."""
    for step in (lambda: None, lambda: proc.send_signal(signal.SIGINT), proc.kill):
        if proc.poll() is not None:
            return
        step()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(BASE_STOP_S / 2)


def _tail(text: str, lines: int = 20) -> str:
    return "\n".join(text.strip().splitlines()[-lines:])


def compare(args: argparse.Namespace, base_commit: str) -> dict[str, Any]:
    """The base's bench, then this code's: always in this order, so that every comparison is made alike, and the
    temporary worktree is gone before this code runs."""
    with base_checkout(base_commit) as checkout:
        argv, dropped = filter_flags(shared_flags(args), help_flags(base_help(checkout)))
        if dropped:
            print(f"bench/push.py: the base's bench does not know {', '.join(dropped)}", file=sys.stderr)
        base = {"commit": base_commit, "dirty": False, "flags": argv, **run_base(checkout, argv)}
    current = {**current_commit(), **run(args)}
    return {"order": ["base", "current"], "dropped_flags": dropped, **merge(base, current)}


def merge(base: dict[str, Any], current: dict[str, Any]) -> dict[str, Any]:
    """Both runs and the ratios base / current (above 1: the current code is faster)."""
    return {"base": base, "current": current,
            "speedup_p50": ratio(base, current, "to_plan_s", "p50"),
            "speedup_end_to_end_p50": ratio(base, current, "latency_s", "p50"),
            "speedup_p95": ratio(base, current, "to_plan_s", "p95"),
            # Without it the ratio may compare different objects (a base without --objects runs them all).
            "same_requests": _requests(base) == _requests(current),
            "speedup_p50_common": common_speedup(base, current)}


def ratio(base: dict[str, Any], current: dict[str, Any], figure: str, stat: str) -> float | None:
    """base[figure][stat] / current[figure][stat]; None when either run served no request (NaN) or lacks it."""
    return divide(base.get(figure, {}).get(stat), current.get(figure, {}).get(stat))


def divide(b: Any, c: Any) -> float | None:
    if not all(isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in (b, c)):
        return None
    return round(b / c, 3)


def common_speedup(base: dict[str, Any], current: dict[str, Any]) -> float | None:
    """The to-plan p50 ratio over only the requests both runs served, from their rows: a fair figure when the
    base pushed more (the same first request pays the one-time loads in both)."""
    b, c = (_to_plan_by_request(side) for side in (base, current))
    common = b.keys() & c.keys()
    if not common:
        return None
    return divide(statistics.median(b[k] for k in common), statistics.median(c[k] for k in common))


def _to_plan_by_request(side: dict[str, Any]) -> dict[tuple[str, float], float]:
    # As `run` sums it: every stage but execution.
    return {(r["object"], r["direction_deg"]): sum(r["stages_s"].get(s, 0.0) for s in STAGES if s != "execution")
            for r in side.get("rows", []) if "stages_s" in r and not r.get("view")}


def _requests(side: dict[str, Any]) -> list[tuple[str, float]]:
    # With --view each request is pushed twice; once is the request.
    return sorted((r["object"], r["direction_deg"]) for r in side.get("rows", []) if not r.get("view"))


def comparison_table(result: dict[str, Any]) -> str:
    """A few lines for a person: the p50/p95 figures of both runs and their ratios."""
    base, current = result["base"], result["current"]
    head = (f"base {base['commit'][:10]}", f"current {current['commit'][:10]}" + ("-dirty" if current["dirty"] else ""))
    lines = [f"{'':<16}{head[0]:>20}{head[1]:>26}{'base/current':>14}"]
    for label, figure, stat, key in (("to plan p50", "to_plan_s", "p50", "speedup_p50"),
                                     ("to plan p95", "to_plan_s", "p95", "speedup_p95"),
                                     ("end to end p50", "latency_s", "p50", "speedup_end_to_end_p50")):
        speedup = result[key]
        lines.append(f"{label:<16}{base.get(figure, {}).get(stat, '-'):>18} s{current[figure][stat]:>24} s"
                     f"{'-' if speedup is None else f'{speedup:.2f}x':>14}")
    lines.append(f"{'requests':<16}{base.get('requests', '-'):>20}{current['requests']:>26}")
    if result["dropped_flags"]:
        lines.append(f"not passed to the base (it does not know them): {', '.join(result['dropped_flags'])}")
    if not result["same_requests"]:
        lines.append(f"the two runs pushed different requests; to plan p50 over the ones both served: "
                     f"{result['speedup_p50_common']}x")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())

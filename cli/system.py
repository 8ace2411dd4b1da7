"""`gd2p up | status | health | demo`: run the local system and look at it over the bus.

    gd2p up [--validators N] [--record-dir DIR] [--listen tcp/127.0.0.1:7447] [--confirm [--confirm-timeout S]]
            [--robot sim|mujoco] [--tracking image|truth]
    gd2p status [--json] [bus flags]          live workers per service (liveliness)
    gd2p health --service S [--worker-id ID | --this-host] [bus flags]   exit 0 iff it answers
    gd2p demo                                  bring the system up, push an object 0.20 m, shut it down

The supervision logic lives in `deploy.launcher.Launcher`; this module only parses and prints.
Heavy imports (zenoh, pydantic models) happen inside the handlers so `gd2p --help` stays fast.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import socket
import sys
import time
from collections.abc import Sequence

CLI_CONNECT_TIMEOUT_MS = 3000  # a CLI must fail clearly, not wait forever, when no router is up
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
SECURE_LISTEN = "tls/localhost:7447"


def register(subparsers: argparse._SubParsersAction) -> None:
    from shared.bus import BusConfig
    from shared.execution.robots import SIM_ROBOTS, TRACKING_MODES

    up = subparsers.add_parser("up", help="start the router and every service locally (Ctrl-C stops all)",
                               description="Start an embedded Zenoh router and every service as its own process; "
                                           "Ctrl-C or SIGTERM stops them all within 10 s.")
    up.add_argument("--validators", type=int, default=None,
                    help=f"validator processes (default: one per core, {os.cpu_count()} here)")
    up.add_argument("--record-dir", default="recordings", help="where the recorder writes MCAP (default %(default)s)")
    up.add_argument("--listen", default=DEFAULT_LISTEN, help="router endpoint (default %(default)s)")
    up.add_argument("--log-dir", default=None, help="per-process log files (default: a new temporary directory)")
    up.add_argument("--ready-timeout", type=float, default=120.0, help="seconds to wait for every worker to register")
    up.add_argument("--secure", action="store_true",
                    help=f"mutual TLS + access control: only the planner may command the robot bridge "
                         f"(router on {SECURE_LISTEN} unless --listen names another tls/ endpoint)")
    up.add_argument("--secure-dir", default="gd2p-secure",
                    help="keys, certificates and Zenoh configs of the secure profile (created once; default %(default)s)")
    up.add_argument("--view", nargs="?", type=int, const=8090, default=None, metavar="PORT",
                    help="also serve the live view in the browser on PORT (default 8090): `gd2p view` attached")
    up.add_argument("--confirm", action="store_true",
                    help="preview and confirm: the robot bridge holds each plan until an operator confirms it "
                         "(gd2p confirm ID); a plan not confirmed in time is dropped (the push answers not_confirmed)."
                         " Off by default for the simulated robot; a hardware bridge confirms by default")
    up.add_argument("--confirm-timeout", type=float, default=None, metavar="S",
                    help="with --confirm: drop a plan not confirmed within S seconds (default 60, at most 240)")
    up.add_argument("--robot", choices=SIM_ROBOTS, default="sim",
                    help="the simulated robot's physics engine: sim (PyBullet, the planner's own; default) or mujoco "
                         "(MuJoCo: plans made in PyBullet execute in an engine nobody tuned them to)")
    up.add_argument("--tracking", choices=TRACKING_MODES, default="image",
                    help="how the simulated robot sees the object while it pushes: image (its model registered in the "
                         "depth frames the engine renders; default) or truth (the simulator's pose plus a little "
                         "noise: quicker, for work on the planner)")
    up.set_defaults(func=run_up)

    status = subparsers.add_parser("status", help="live worker count per service",
                                   description="Count the live workers of every service from their liveliness tokens.")
    status.add_argument("--json", action="store_true", help='print {"service": count, ...}')
    BusConfig.add_cli_args(status)
    status.set_defaults(func=run_status)

    health = subparsers.add_parser("health", help="exit 0 iff a worker of SERVICE answers a health query",
                                   description="Send a HealthQuery to the workers of a service and print their "
                                               "WorkerStatus; exit 0 iff at least one ready worker answered.")
    health.add_argument("--service", required=True, help="service name, e.g. validator")
    who = health.add_mutually_exclusive_group()
    who.add_argument("--worker-id", default=None, help="ask only this worker")
    who.add_argument("--this-host", action="store_true",
                     help="only workers running on this host (container healthchecks)")
    health.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for answers (default %(default)s)")
    BusConfig.add_cli_args(health)
    health.set_defaults(func=run_health)

    demo = subparsers.add_parser("demo", help="bring the system up, push a bundled object 0.20 m, shut it down",
                                 description="The push demo: start every service, push a bundled box 0.20 m with "
                                             "the shipped checkpoint (or, without one, the fixed spatula pose — "
                                             "said plainly), print the result and where the MCAP and PNG are, "
                                             "stop cleanly.")
    demo.add_argument("--validators", type=int, default=1, help="validator processes (default %(default)s)")
    demo.add_argument("--record-dir", default="recordings", help="where the recorder writes MCAP (default %(default)s)")
    demo.set_defaults(func=run_demo)


# ---------------------------------------------------------------------------------------------
# bus look-ups shared by the commands
# ---------------------------------------------------------------------------------------------


def worker_statuses(session, service: str | None = None, worker_id: str | None = None, timeout: float = 5.0) -> list:
    """WorkerStatus of every worker of `service` (of `worker_id` only, if given) that answers in time."""
    from shared.bus import health
    from shared.contracts.messages import WorkerStatus

    statuses = [s for s in health(session, service, timeout=timeout) if isinstance(s, WorkerStatus)]
    return [s for s in statuses if worker_id is None or s.worker_id == worker_id]


def _cli_bus_config(args: argparse.Namespace):
    from shared.bus import BusConfig

    return BusConfig.from_args(args, connect_timeout_ms=CLI_CONNECT_TIMEOUT_MS)


def _status_rows(statuses: list) -> list[tuple[str, ...]]:
    rows: list[tuple[str, ...]] = [("SERVICE", "WORKER", "PID", "HOST", "STATE", "UPTIME_S", "DONE", "FAILED")]
    for s in statuses:
        rows.append((s.service, s.worker_id, str(s.pid), s.host, s.state, f"{s.uptime_s:.1f}",
                     str(s.jobs_done), str(s.jobs_failed)))
    return rows


def _print_table(rows: Sequence[tuple[str, ...]], indent: str = "") -> None:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print(indent + "  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)).rstrip())


# ---------------------------------------------------------------------------------------------
# gd2p status / health
# ---------------------------------------------------------------------------------------------


def service_counts(session, timeout: float = 2.0) -> dict[str, int]:
    """Live worker count of every known service (0 when absent), then any other service seen."""
    from deploy.launcher import SERVICES
    from shared.bus import live_workers

    live = live_workers(session, timeout=timeout)
    counts = {svc: len(live.get(svc, [])) for svc in SERVICES}
    counts.update({svc: len(ids) for svc, ids in live.items() if svc not in counts})
    return counts


def run_status(args: argparse.Namespace) -> int:
    from shared.bus import BusError, open_session

    try:
        cfg = _cli_bus_config(args)
        with open_session(cfg) as session:
            counts = service_counts(session)
    except BusError as exc:
        print(f"gd2p status: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(counts))
    else:
        _print_table([("SERVICE", "WORKERS")] + [(svc, str(n)) for svc, n in counts.items()])
    return 0


def run_health(args: argparse.Namespace) -> int:
    from shared.bus import BusError, open_session

    try:
        with open_session(_cli_bus_config(args)) as session:
            statuses = worker_statuses(session, args.service, args.worker_id, timeout=args.timeout)
    except BusError as exc:
        print(f"gd2p health: {exc}", file=sys.stderr)
        return 1
    if args.this_host:
        statuses = [s for s in statuses if s.host == socket.gethostname()]
    healthy = [s for s in statuses if s.state in ("ready", "busy")]
    if statuses:
        _print_table(_status_rows(statuses))
    if not healthy:
        who = args.worker_id or ("on this host" if args.this_host else "at all")
        print(f"gd2p health: no ready {args.service} worker answered ({who}) within {args.timeout:g} s",
              file=sys.stderr)
        return 1
    return 0


# ---------------------------------------------------------------------------------------------
# gd2p up
# ---------------------------------------------------------------------------------------------


def _interrupt(signum: int, frame) -> None:
    raise KeyboardInterrupt


def run_up(args: argparse.Namespace) -> int:
    from deploy.launcher import Launcher, LaunchError

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    signal.signal(signal.SIGTERM, _interrupt)  # SIGTERM stops like Ctrl-C
    from shared.execution.confirm import DEFAULT_TIMEOUT_S, MAX_TIMEOUT_S

    confirm = getattr(args, "confirm", False)
    confirm_timeout = getattr(args, "confirm_timeout", None)
    if confirm_timeout is not None and not confirm:
        print("gd2p up: --confirm-timeout needs --confirm", file=sys.stderr)
        return 2
    confirm_timeout = DEFAULT_TIMEOUT_S if confirm_timeout is None else confirm_timeout
    if confirm and not 0.0 < confirm_timeout <= MAX_TIMEOUT_S:
        print(f"gd2p up: --confirm-timeout must be in (0, {MAX_TIMEOUT_S:g}] s (the planner waits 300 s for a command)",
              file=sys.stderr)
        return 2
    try:
        secure = getattr(args, "secure", False)
        listen = SECURE_LISTEN if secure and args.listen == DEFAULT_LISTEN else args.listen
        # Each push request's MCAP + storyboard go beside the bus recording (the planner child inherits this).
        os.environ.setdefault("GD2P_PUSH_RECORD_DIR", os.path.join(os.path.abspath(args.record_dir), "pushes"))
        launcher = Launcher(validators=args.validators, listen=listen, record_dir=args.record_dir,
                            log_dir=args.log_dir, secure_dir=args.secure_dir if secure else None,
                            view_port=getattr(args, "view", None),
                            confirm_timeout_s=confirm_timeout if confirm else None,
                            robot=getattr(args, "robot", "sim"), tracking=getattr(args, "tracking", "image"))
    except LaunchError as exc:
        print(f"gd2p up: {exc}", file=sys.stderr)
        return 2
    code = 0
    try:
        launcher.start()
        t0 = time.monotonic()
        launcher.wait_ready(args.ready_timeout)
        print(f"all {len(launcher.children())} workers registered in {time.monotonic() - t0:.1f} s\n")
        print(launcher.table())
        print(f"\nrouter: {launcher.listen}   recordings: {launcher.record_dir}   logs: {launcher.log_dir}")
        if launcher.view_url is not None:
            print(f"live view: {launcher.view_url}")
        tools = scale = f"--connect {launcher.endpoint}"
        if launcher.secure is not None:
            # The operator's everyday tools join as "cli"; only the "operator" identity may scale (and confirm).
            tools += f" --zenoh-config {launcher.secure.client_config('cli')}"
            scale += f" --zenoh-config {launcher.secure.client_config('operator')}"
            print(f"secure profile: mTLS + access control from {launcher.secure.directory} "
                  f"(CA key in {launcher.secure.ca_dir}: keep it offline)")
        print(f"status: gd2p status {tools}   scale: python deploy/scale_validators.py N {scale}")
        if confirm:
            print(f"preview and confirm: each plan waits up to {confirm_timeout:g} s for "
                  f"`gd2p confirm ID {scale}` (held plans: gd2p confirm --list {scale})")
        print("Ctrl-C (or SIGTERM) stops everything.", flush=True)
        while True:
            time.sleep(3600)  # the launcher's threads supervise; a signal ends the wait
    except KeyboardInterrupt:
        print("\nstopping ...", flush=True)
    except LaunchError as exc:
        print(f"gd2p up: {exc}", file=sys.stderr)
        code = 1
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)  # a second Ctrl-C must not cut the shutdown short
        t0 = time.monotonic()
        launcher.stop()
        print(f"stopped in {time.monotonic() - t0:.1f} s")
    return code


# ---------------------------------------------------------------------------------------------
# gd2p demo
# ---------------------------------------------------------------------------------------------


DEMO_OBJECT = "proc-box-013"  # a procedural box of the test split (never trained on): 13.9 x 4.6 x 7.5 cm
DEMO_DIRECTION_DEG = 90.0  # sideways across the table in front of the robot
DEMO_DISTANCE_M = 0.20


def run_demo(args: argparse.Namespace) -> int:
    """Push demo: bring the system up, push a bundled object 0.20 m, print the result and recordings, shut down."""
    from deploy.launcher import Launcher, LaunchError, free_loopback_endpoint
    from shared.sampling.checkpoint import default_checkpoint_path

    checkpoint = default_checkpoint_path("allegro")
    method = "gd2p" if checkpoint.is_file() else "fixed"
    print("GD2P demo: the robot pushes a bundled object 0.20 m (simulated Panda + Allegro).")
    if method == "gd2p":
        print(f"Hand poses: sampled by the diffusion model ({checkpoint}).")
    else:
        print(f"NOTE: no Allegro checkpoint at {checkpoint}, so this demo does NOT use the diffusion model: it falls")
        print("      back to the fixed spatula hand pose (the paper's baseline). Train or install a checkpoint")
        print("      (`gd2p train --hand allegro --out ...`) to see GD2P's sampled poses.")
    record_dir = os.path.abspath(args.record_dir)
    os.environ["GD2P_PUSH_RECORD_DIR"] = os.path.join(record_dir, "pushes")  # the planner child inherits it
    launcher = Launcher(validators=args.validators, listen=free_loopback_endpoint(), record_dir=record_dir)
    t0 = time.monotonic()
    try:
        launcher.start()
        launcher.wait_ready(120.0)
        print(f"\n1. started an embedded router on {launcher.listen} and {len(launcher.children())} service "
              f"processes in {time.monotonic() - t0:.1f} s.")
        ok = _demo_push(launcher, method)
    except LaunchError as exc:
        print(f"gd2p demo: {exc}", file=sys.stderr)
        ok = False
    finally:
        t1 = time.monotonic()
        launcher.stop()
        print(f"\n3. stopped every process and the router in {time.monotonic() - t1:.1f} s.")
    return 0 if ok else 1


def _demo_push(launcher, method: str) -> bool:
    from cli.push import describe
    from client.push_client import PushFailed, push
    from shared.bus import BusConfig
    from shared.contracts.messages import ObjectRef, PlannerOptions, PushRequest

    request = PushRequest(object=ObjectRef(library_id=DEMO_OBJECT), direction_deg=DEMO_DIRECTION_DEG,
                          distance_m=DEMO_DISTANCE_M,
                          options=PlannerOptions(method=method))
    print(f"2. push request: {DEMO_OBJECT} at the default spot, {DEMO_DISTANCE_M:.2f} m toward "
          f"{DEMO_DIRECTION_DEG:.0f} deg, pose source {method!r} (planning, arm rollouts, ranking, execution)...")
    cfg = BusConfig(mode="client", connect=[launcher.endpoint], connect_timeout_ms=CLI_CONNECT_TIMEOUT_MS)
    try:
        response = push(request, cfg, timeout_s=600.0)
    except PushFailed as exc:
        print(f"   -> the request failed: {exc}", file=sys.stderr)
        return False
    print("   " + describe(response).replace("\n", "\n   "))
    _wait_for_storyboard(response.recording_path)
    return response.success


def _wait_for_storyboard(recording_path: str | None, timeout_s: float = 60.0) -> None:
    """The planner renders the storyboard just after answering: let it finish before shutting down."""
    if recording_path is None:
        return
    png = os.path.splitext(recording_path)[0] + ".png"
    deadline = time.monotonic() + timeout_s
    while not os.path.isfile(png) and time.monotonic() < deadline:
        time.sleep(0.2)
    if not os.path.isfile(png):
        print(f"   (the storyboard {png} was not written within {timeout_s:.0f} s)", file=sys.stderr)



"""Local launcher: an embedded Zenoh router plus every service as its own supervised process.

    launcher = Launcher(validators=2, listen="tcp/127.0.0.1:7447")
    launcher.start()              # router up, every service spawned
    launcher.wait_ready(60)       # every worker registered (liveliness), or LaunchError
    launcher.scale("validator", 4)
    launcher.stop()               # SIGTERM all, SIGKILL stragglers, router closed: < 10 s

The router is a Python Zenoh session in router mode on loopback (no `zenohd` is installed here).
Each service runs as `python -m services.<name> --mode client --connect <router> --worker-id ID`,
started through `deploy.child_guard` so that no worker outlives the launcher. A crashed service is
restarted with exponential backoff. The launcher also serves `gd2p/launcher/control`: a
`ScaleRequest` brings a scalable service to exactly N workers and is answered with a `ScaleReply`
(what `deploy/scale_validators.py` uses against a running `gd2p up`). A request above the service's
configured maximum (`scale_limits`: by default 4 validators per core and max(2, cores) of every other
scalable service; `GD2P_MAX_SCALE="validator=16,planner=3"` or `Launcher(max_scale=...)` changes it)
is refused with ErrorReply "bad_request" naming the limit; ScaleRequest's own bound (1024) stays the
hard cap. Under the secure profile only the "operator" identity may reach the control key.
"""
from __future__ import annotations

import itertools
import logging
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from shared.bus import DEFAULT_ROUTER_ENDPOINT, BusConfig, BusError, RemoteError, live_workers, open_session
from shared.bus.interfaces import LAUNCHER_CONTROL_KEY as CONTROL_KEY  # the control key, as the registry spells it
from shared.bus.interfaces import SERVICES  # the services the launcher runs, in start order
from shared.contracts.codec import CodecError, decode, encode
from shared.contracts.messages import ErrorReply, Message, ScaleReply, ScaleRequest
from shared.execution.robots import SIM_ROBOTS, TRACKING_MODES

log = logging.getLogger("gd2p.launcher")

# Stateless job servers behind the dispatcher. The robot bridge (one robot) and the recorder
# (one recording) are singletons.
SCALABLE: frozenset[str] = frozenset({"generator", "validator", "sampler", "planner"})
MAX_SCALE_ENV = "GD2P_MAX_SCALE"  # e.g. "validator=16,planner=3": the most workers a scale request may ask for
# ScaleRequest's own bound on `count`: no configured maximum may exceed it.
SCALE_HARD_CAP: int = next(m.le for m in ScaleRequest.model_fields["count"].metadata if hasattr(m, "le"))

STOP_TIMEOUT_S = 10.0
_POLL_S = 0.2
_BACKOFF_START_S = 1.0
_BACKOFF_MAX_S = 30.0
_STABLE_AFTER_S = 30.0  # a child that ran this long before crashing restarts without backoff
_PROJECT_ROOT = Path(__file__).resolve().parents[1]


class LaunchError(RuntimeError):
    """The system could not be brought up, scaled or reached as asked."""


@dataclass
class Child:
    """One service process and what the supervisor knows about it."""

    service: str
    worker_id: str
    seq: int  # creation order within the service
    log_path: Path
    process: subprocess.Popen
    started_at: float = field(default_factory=time.monotonic)
    restarts: int = 0
    crash_streak: int = 0
    restart_at: float | None = None  # set while waiting to restart after a crash

    @property
    def pid(self) -> int:
        return self.process.pid


@dataclass
class ChildExit:
    """An unexpected exit, kept for `wait_ready` and for the operator."""

    service: str
    worker_id: str
    returncode: int
    log_tail: str
    at: float = field(default_factory=time.monotonic)

    def describe(self) -> str:
        tail = self.log_tail.strip() or "(no output)"
        return f"{self.service} ({self.worker_id}) exited with code {self.returncode}; last output:\n{tail}"


def default_scale_limits(cpus: int | None = None) -> dict[str, int]:
    """The most workers of each scalable service a scale request may ask for on a machine with `cpus`
    cores: 4 validators per core (rollouts are short and mostly wait), max(2, cores) of the others
    (each generator, sampler or planner process can keep a core busy). 2 cores: 8 validators, 2 of the rest."""
    cpus = max(1, cpus or os.cpu_count() or 1)
    return {svc: 4 * cpus if svc == "validator" else max(2, cpus) for svc in sorted(SCALABLE)}


def parse_scale_limits(text: str) -> dict[str, int]:
    """'validator=16,planner=3' -> {'validator': 16, 'planner': 3}; LaunchError naming what is wrong."""
    limits: dict[str, int] = {}
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        service, sep, value = item.partition("=")
        service = service.strip()
        if not sep or service not in SCALABLE:
            raise LaunchError(f"bad scale limit {item!r}: expected SERVICE=N with SERVICE one of "
                              f"{', '.join(sorted(SCALABLE))}")
        try:
            count = int(value)
        except ValueError:
            raise LaunchError(f"bad scale limit {item!r}: {value.strip()!r} is not an integer") from None
        if not 0 <= count <= SCALE_HARD_CAP:
            raise LaunchError(f"bad scale limit {item!r}: the maximum must be between 0 and {SCALE_HARD_CAP}")
        limits[service] = count
    return limits


def scale_limits(overrides: Mapping[str, int] | None = None, environ: Mapping[str, str] | None = None,
                 cpus: int | None = None) -> dict[str, int]:
    """Per scalable service, the most workers a scale request may ask for: the defaults
    (`default_scale_limits`), then `GD2P_MAX_SCALE` from `environ`, then `overrides`."""
    env = os.environ if environ is None else environ
    limits = default_scale_limits(cpus)
    try:
        limits.update(parse_scale_limits(env.get(MAX_SCALE_ENV, "")))
    except LaunchError as exc:
        raise LaunchError(f"{MAX_SCALE_ENV}: {exc}") from None
    if overrides:
        limits.update(parse_scale_limits(",".join(f"{svc}={n}" for svc, n in overrides.items())))
    return limits


def client_endpoint(listen: str) -> str:
    """Where a local client connects for a router listening on `listen` (wildcard -> loopback)."""
    return listen.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]")


def free_loopback_endpoint() -> str:
    """A tcp endpoint on a currently free loopback port (for demos and tests)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def log_tail(path: Path, max_lines: int = 20, max_bytes: int = 8192) -> str:
    """The last lines of a child's log file ('' if there is none)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - max_bytes))
            lines = f.read().decode("utf-8", "replace").splitlines()
    except OSError:
        return ""
    return "\n".join(lines[-max_lines:])


def terminate(processes: list[subprocess.Popen], grace_s: float) -> list[subprocess.Popen]:
    """SIGTERM every process, wait up to `grace_s`, SIGKILL the rest; returns the ones killed."""
    for p in processes:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and any(p.poll() is None for p in processes):
        time.sleep(0.05)
    killed = [p for p in processes if p.poll() is None]
    for p in killed:
        p.kill()
    for p in processes:
        p.wait()
    return killed


class Launcher:
    """The embedded router and the supervised service processes of one local system."""

    def __init__(
        self,
        validators: int | None = None,
        listen: str = DEFAULT_ROUTER_ENDPOINT,
        record_dir: str | os.PathLike = "recordings",
        log_dir: str | os.PathLike | None = None,
        restart: bool = True,
        secure_dir: str | os.PathLike | None = None,
        max_scale: Mapping[str, int] | None = None,
        view_port: int | None = None,
        confirm_timeout_s: float | None = None,
        robot: str = "sim",
        tracking: str = "image",
    ):
        # The most workers per scalable service (defaults, GD2P_MAX_SCALE, then `max_scale`).
        self.max_scale = scale_limits(max_scale)
        n_validators = min(os.cpu_count() or 1, self.max_scale["validator"]) if validators is None else validators
        if n_validators < 0:
            raise LaunchError(f"the number of validators must be >= 0, got {n_validators}")
        if (refusal := self.scale_refusal("validator", n_validators)) is not None:
            raise LaunchError(refusal)
        self.listen = listen
        self.endpoint = client_endpoint(listen)
        self.record_dir = Path(record_dir).resolve()
        self.log_dir = Path(log_dir) if log_dir else Path(tempfile.mkdtemp(prefix="gd2p-up-logs-"))
        self.restart = restart
        # Secure profile (deploy/secure): mTLS router with access control; each service joins with its
        # own certificate, so only the planner may command the robot bridge.
        self.secure = None
        if secure_dir is not None:
            if not listen.startswith("tls/"):
                raise LaunchError(f"the secure profile listens on a tls/ endpoint, got {listen}")
            from deploy.secure import prepare

            self.secure = prepare(secure_dir, [listen])
        # Preview and confirm: the bridge holds each plan for an operator, at most this long (None: off).
        self.confirm_timeout_s = confirm_timeout_s
        # The simulated robot's engine (`gd2p up --robot`): the bridge builds PyBullet's or MuJoCo's.
        if robot not in SIM_ROBOTS:
            raise LaunchError(f"unknown simulated robot {robot!r}; known: {', '.join(SIM_ROBOTS)}")
        if tracking not in TRACKING_MODES:
            raise LaunchError(f"unknown tracking {tracking!r}; known: {', '.join(TRACKING_MODES)}")
        self.robot, self.tracking = robot, tracking
        self.initial_counts = {svc: 1 for svc in SERVICES} | {"validator": n_validators}
        self.exits: list[ChildExit] = []
        self._children: dict[str, Child] = {}  # worker id -> child
        self._numbers = {svc: itertools.count(1) for svc in SERVICES}
        self._lock = threading.RLock()
        self._scale_lock = threading.Lock()
        self._stopping = threading.Event()
        self._exits_checked_since = time.monotonic()  # wait_ready reports exits after this
        self._session: zenoh.Session | None = None
        self._control: zenoh.Queryable | None = None
        self._threads: list[threading.Thread] = []
        # One long-lived thread spawns every child: child_guard's parent-death signal follows the
        # spawning thread, so a short-lived caller thread must never be the one that forks.
        self._spawner = ThreadPoolExecutor(max_workers=1, thread_name_prefix="gd2p-spawner")
        # The live view (`gd2p up --view [PORT]`, cli/view.py): a process beside the services, not a worker.
        self.view_port = view_port
        self._view: subprocess.Popen | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Open the router, serve the control key, spawn every service, start supervising."""
        if self._session is not None:
            raise LaunchError("launcher already started")
        self.record_dir.mkdir(parents=True, exist_ok=True)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self._exits_checked_since = time.monotonic()
        try:
            router_file = str(self.secure.router_config) if self.secure else None
            self._session = open_session(BusConfig(mode="router", listen=[self.listen], connect=[],
                                                   config_file=router_file))
        except BusError as exc:
            raise LaunchError(f"cannot start the router on {self.listen} (is another `gd2p up` running?): {exc}") from None
        self._control = self._session.declare_queryable(CONTROL_KEY, complete=True)
        self._start_thread(self._serve_control, "gd2p-launcher-control")
        with self._lock:
            for service, count in self.initial_counts.items():
                for _ in range(count):
                    self._spawn(service)
        self._start_thread(self._supervise, "gd2p-launcher-supervisor")
        if self.view_port is not None:
            self._start_view(self.view_port)
        log.info("router on %s; services starting (logs in %s)", self.listen, self.log_dir)

    def wait_ready(self, timeout: float = 60.0) -> dict[str, list[str]]:
        """Block until every child has registered; returns {service: worker ids}.

        Raises LaunchError naming the service and its last output if a child exits meanwhile,
        or naming the missing workers on timeout.
        """
        deadline = time.monotonic() + timeout
        while True:
            self._raise_on_exit_since(self._exits_checked_since)
            expected = self.expected_workers()
            live = self.live_workers()
            missing = {svc: sorted(set(ids) - set(live.get(svc, []))) for svc, ids in expected.items()}
            missing = {svc: ids for svc, ids in missing.items() if ids}
            if not missing:
                self._exits_checked_since = time.monotonic()
                return expected
            if time.monotonic() > deadline:
                raise LaunchError(f"not registered after {timeout:.0f} s: {missing} (logs in {self.log_dir})")
            time.sleep(_POLL_S)

    def stop(self, timeout: float = STOP_TIMEOUT_S) -> None:
        """Stop every service (recorder last, so it records until the end), then the router."""
        if self._stopping.is_set():
            return
        self._stopping.set()
        t0 = time.monotonic()
        if self._control is not None:
            self._control.undeclare()  # ends the control thread's loop
        for thread in self._threads:
            thread.join(timeout=2.0)
        with self._lock:
            children = list(self._children.values())
            self._children.clear()
        workers = [c.process for c in children if c.service != "recorder"]
        recorders = [c.process for c in children if c.service == "recorder"]
        deadline = t0 + max(1.0, timeout - 1.0)  # keep a second for SIGKILL, reaping and the router
        if self._view is not None:
            workers.append(self._view)
        killed = terminate(workers, grace_s=max(0.2, (deadline - time.monotonic()) / 2))
        killed += terminate(recorders, grace_s=max(0.2, deadline - time.monotonic()))
        if killed:
            log.warning("killed %d process(es) that ignored SIGTERM: pids %s", len(killed), [p.pid for p in killed])
        self._spawner.shutdown(wait=True)
        if self._session is not None:
            self._session.close()
        log.info("stopped %d process(es) and the router in %.1f s", len(children), time.monotonic() - t0)

    def __enter__(self) -> Launcher:
        self.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self.stop()

    # ------------------------------------------------------------------ queries
    @property
    def session(self) -> zenoh.Session:
        """The router's own session (usable as a bus session by in-process callers)."""
        if self._session is None:
            raise LaunchError("launcher not started")
        return self._session

    def expected_workers(self) -> dict[str, list[str]]:
        """{service: worker ids} of the processes this launcher runs."""
        with self._lock:
            children = list(self._children.values())
        expected: dict[str, list[str]] = {svc: [] for svc in SERVICES}
        for child in children:
            expected[child.service].append(child.worker_id)
        return {svc: sorted(ids) for svc, ids in expected.items()}

    def live_workers(self, timeout: float = 1.0) -> dict[str, list[str]]:
        """{service: worker ids} registered on the bus right now (liveliness)."""
        return live_workers(self.session, timeout=timeout)

    def children(self) -> list[Child]:
        with self._lock:
            return sorted(self._children.values(), key=lambda c: (SERVICES.index(c.service), c.seq))

    def table(self) -> str:
        """A readable table of every service process: worker id, pid, registered or not, restarts."""
        live = self.live_workers()
        rows = [("SERVICE", "WORKER", "PID", "STATE", "RESTARTS", "LOG")]
        for c in self.children():
            if c.restart_at is not None:
                state = "restarting"
            else:
                state = "ready" if c.worker_id in live.get(c.service, []) else "starting"
            rows.append((c.service, c.worker_id, str(c.pid), state, str(c.restarts), str(c.log_path)))
        widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
        return "\n".join("  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)).rstrip() for row in rows)

    # ------------------------------------------------------------------ scaling
    def scale_refusal(self, service: str, count: int) -> str | None:
        """Why `service` may not be brought to `count` workers (None if it may)."""
        if service not in SCALABLE:
            return f"cannot scale {service!r}: scalable services are {', '.join(sorted(SCALABLE))}"
        if count < 0:
            return f"cannot scale {service} to {count}: the count must be >= 0"
        limit = self.max_scale[service]
        if count > limit:
            return (f"cannot scale {service} to {count}: the maximum on this launcher is {limit} "
                    f"(set {MAX_SCALE_ENV}=\"{service}=N\" when starting `gd2p up` to change it)")
        return None

    def scale(self, service: str, count: int, ready_timeout: float = 60.0) -> ScaleReply:
        """Bring `service` to exactly `count` processes; new ones are registered on return.
        LaunchError if the service is not scalable or `count` is negative or above `max_scale`."""
        if (refusal := self.scale_refusal(service, count)) is not None:
            raise LaunchError(refusal)
        with self._scale_lock:
            if self._stopping.is_set():
                raise LaunchError("launcher is stopping")
            with self._lock:
                current = sorted((c for c in self._children.values() if c.service == service), key=lambda c: c.seq)
                started = [self._spawn(service).worker_id for _ in range(count - len(current))]
                leaving = current[count:]  # the newest go first: the oldest have the warmest caches
                for child in leaving:
                    del self._children[child.worker_id]
            terminate([c.process for c in leaving], grace_s=STOP_TIMEOUT_S / 2)
            if started:
                self._wait_registered(service, started, ready_timeout)
            log.info("%s scaled to %d (started %s, stopped %s)", service, count, started, [c.worker_id for c in leaving])
            return ScaleReply(service=service, count=count, started=started, stopped=[c.worker_id for c in leaving])

    def _wait_registered(self, service: str, worker_ids: list[str], timeout: float) -> None:
        since = time.monotonic()
        while True:
            if self._stopping.is_set():
                raise LaunchError("launcher is stopping")
            self._raise_on_exit_since(since, worker_ids)
            missing = set(worker_ids) - set(live_workers(self.session, service).get(service, []))
            if not missing:
                return
            if time.monotonic() - since > timeout:
                raise LaunchError(f"{service} workers {sorted(missing)} not registered after {timeout:.0f} s")
            time.sleep(_POLL_S)

    # ------------------------------------------------------------------ processes
    def _command(self, service: str, worker_id: str) -> list[str]:
        cmd = [sys.executable, "-m", "deploy.child_guard", str(os.getpid()), f"services.{service}",
               "--mode", "client", "--connect", self.endpoint, "--worker-id", worker_id]
        if service == "recorder":
            cmd += ["--record-dir", str(self.record_dir)]
        if service == "robot_bridge":  # the simulated robot: confirm only when asked (`gd2p up --confirm`)
            cmd += ["--robot", self.robot, "--tracking", self.tracking]
            cmd += (["--confirm", "--confirm-timeout", f"{self.confirm_timeout_s:g}"] if self.confirm_timeout_s
                    else ["--no-confirm"])
        if self.secure is not None:
            cmd += ["--zenoh-config", str(self.secure.client_config(service))]
        return cmd

    @property
    def view_url(self) -> str | None:
        return None if self.view_port is None else f"http://127.0.0.1:{self.view_port}"

    def _start_view(self, port: int) -> None:
        """The live view's process (cli/view.py) on `port`, joined as the operator (its Confirm button)."""
        cmd = [sys.executable, "-m", "deploy.child_guard", str(os.getpid()), "cli.view", "--port", str(port),
               "--mode", "client", "--connect", self.endpoint]
        if self.secure is not None:
            cmd += ["--zenoh-config", str(self.secure.client_config("operator"))]
        with open(self.log_dir / "view.log", "ab") as out:
            self._view = self._spawner.submit(subprocess.Popen, cmd, stdin=subprocess.DEVNULL, stdout=out,
                                              stderr=subprocess.STDOUT, env=self._environment(),
                                              start_new_session=True).result()

    def _environment(self) -> dict[str, str]:
        env = dict(os.environ)
        env.setdefault("OMP_NUM_THREADS", "1")  # several busy processes share the cores (docs/architecture.md §Compute)
        env["PYTHONUNBUFFERED"] = "1"  # a crash's last words reach the log before it dies
        # The children import the project the same way this process did, installed or not.
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(_PROJECT_ROOT), env.get("PYTHONPATH")) if p)
        return env

    def _popen(self, service: str, worker_id: str, log_path: Path) -> subprocess.Popen:
        with open(log_path, "ab") as out:
            return self._spawner.submit(
                subprocess.Popen, self._command(service, worker_id), stdin=subprocess.DEVNULL,
                stdout=out, stderr=subprocess.STDOUT, env=self._environment(),
                start_new_session=True,  # Ctrl-C reaches only the launcher, which stops the rest in order
            ).result()

    def _spawn(self, service: str) -> Child:
        seq = next(self._numbers[service])
        worker_id = f"{service}-{seq}"
        log_path = self.log_dir / f"{worker_id}.log"
        child = Child(service, worker_id, seq, log_path, self._popen(service, worker_id, log_path))
        self._children[worker_id] = child
        log.debug("started %s as pid %d", worker_id, child.pid)
        return child

    def _raise_on_exit_since(self, since: float, worker_ids: list[str] | None = None) -> None:
        for exit_ in list(self.exits):
            if exit_.at >= since and (worker_ids is None or exit_.worker_id in worker_ids):
                raise LaunchError(f"{exit_.describe()}\n(full log: {self.log_dir / (exit_.worker_id + '.log')})")

    # ------------------------------------------------------------------ supervision
    def _supervise(self) -> None:
        while not self._stopping.wait(_POLL_S):
            with self._lock:
                for child in list(self._children.values()):
                    if self._stopping.is_set():
                        return
                    self._check(child)

    def _check(self, child: Child) -> None:
        now = time.monotonic()
        if child.restart_at is not None:
            if now >= child.restart_at:
                child.process = self._popen(child.service, child.worker_id, child.log_path)
                child.started_at, child.restart_at = now, None
                child.restarts += 1
                log.warning("restarted %s as pid %d (restart #%d)", child.worker_id, child.pid, child.restarts)
            return
        code = child.process.poll()
        if code is None:
            return
        exit_ = ChildExit(child.service, child.worker_id, code, log_tail(child.log_path))
        self.exits.append(exit_)
        log.error("%s", exit_.describe())
        if not self.restart:
            del self._children[child.worker_id]
            return
        child.crash_streak = 1 if now - child.started_at > _STABLE_AFTER_S else child.crash_streak + 1
        delay = min(_BACKOFF_MAX_S, _BACKOFF_START_S * 2 ** (child.crash_streak - 1))
        child.restart_at = now + delay
        log.warning("restarting %s in %.0f s", child.worker_id, delay)

    # ------------------------------------------------------------------ control key
    def _serve_control(self) -> None:
        assert self._control is not None
        for query in self._control:
            try:
                reply = self._handle_control(query)
                payload, encoding = encode(reply)
                query.reply(CONTROL_KEY, payload, encoding=encoding)
            except zenoh.ZError as exc:  # the caller went away
                log.debug("control reply not delivered: %s", exc)
            finally:
                query.drop()

    def _handle_control(self, query: zenoh.Query) -> Message:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        encoding = str(query.encoding) if query.encoding is not None else None
        try:
            request = decode(payload, encoding, expected=ScaleRequest)
        except CodecError as exc:
            return ErrorReply(code="bad_request", message=str(exc), service="launcher")
        if not isinstance(request, ScaleRequest):
            return ErrorReply(code="bad_request", message=f"the launcher accepts ScaleRequest; got {type(request).__name__}",
                              service="launcher", id=request.id)
        def refuse(code: str, message: str) -> ErrorReply:
            return ErrorReply(code=code, message=message, service="launcher", id=request.id, request_type="ScaleRequest")

        if (refusal := self.scale_refusal(request.service, request.count)) is not None:
            return refuse("bad_request", refusal)
        if self._stopping.is_set():
            return refuse("unavailable", "the launcher is stopping")
        try:
            return self.scale(request.service, request.count).model_copy(update={"id": request.id})
        except Exception as exc:  # the control loop must outlive any one failed request
            log.exception("scale request %s failed", request.id)
            return refuse("internal", str(exc) if isinstance(exc, LaunchError) else repr(exc))

    def _start_thread(self, target, name: str) -> None:
        thread = threading.Thread(target=target, name=name, daemon=True)
        thread.start()
        self._threads.append(thread)


def request_scale(session: zenoh.Session, service: str, count: int, timeout: float = 120.0) -> ScaleReply:
    """Ask a running launcher (over the bus) to bring `service` to exactly `count` workers.

    Raises RemoteError if the launcher refuses, LaunchError if no launcher answers.
    """
    payload, encoding = encode(ScaleRequest(service=service, count=count))
    for reply in session.get(CONTROL_KEY, payload=payload, encoding=encoding, timeout=timeout):
        if reply.ok is None:
            continue
        answer = decode(reply.ok.payload.to_bytes(), str(reply.ok.encoding), expected=ScaleReply)
        if isinstance(answer, ErrorReply):
            raise RemoteError(answer)
        return answer
    raise LaunchError(f"no launcher answered on {CONTROL_KEY} within {timeout:.0f} s: is `gd2p up` running?")

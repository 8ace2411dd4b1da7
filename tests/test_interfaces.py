"""The interface registry (shared/bus/interfaces.py) against everything that restates it.

- offline: every key of shared/bus/keys.py has its row; every row's declarers and callers are exactly
  what the secure profile's rules allow, and the rules grant nothing more than the rows (but the grants
  listed in UNUSED_GRANTS); the launcher's and compose's service lists; every message of
  shared/contracts/messages.py travels somewhere; docs/interfaces.md is the generated text; the documented example
  map decodes; examples/raw_zenoh_push.py imports only zenoh, msgpack and the standard library;
- live, on the conftest router with a worker of every service in threads (planner, validator and
  robot bridge as in tests/test_push.py, plus generator, sampler and recorder): the example pushes the
  box; every publication and token seen meanwhile has its row with the row's message type; every
  worker accepts exactly its row's requests; the robot command key takes ExecutionCommands only.
"""
from __future__ import annotations

import ast
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import pytest
import yaml
import zenoh

from shared.bus import BusConfig, health, keys, live_workers, open_session
from shared.bus import interfaces as registry
from shared.bus.interfaces import INTERFACES, WORKERS, interface
from shared.bus.lease import LEASE_ROLES, lease_key
from shared.contracts.codec import ENCODING_PREFIX, decode, encode
from shared.contracts.messages import MESSAGE_TYPES, ErrorReply, HealthQuery, PushRequest, ScaleRequest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "raw_zenoh_push.py"
TRACKER_EXAMPLE = ROOT / "examples" / "object_tracker.py"

# (flow, message) of the router's access rules that each role of a row needs, by the row's kind.
ROLE_MESSAGES = {
    "queryable": {"declarers": {("ingress", "declare_queryable"), ("ingress", "reply"), ("egress", "query")},
                  "callers": {("ingress", "query"), ("egress", "reply")}},
    "publication": {"declarers": {("ingress", "put")},
                    "callers": {("ingress", "declare_subscriber"), ("egress", "put")}},
    "liveliness": {"declarers": {("ingress", "liveliness_token")},
                   "callers": {("ingress", "liveliness_query"), ("ingress", "declare_liveliness_subscriber"),
                               ("egress", "liveliness_token")}},
}
# What a session may send that makes something happen on a key (observing is open to all on gd2p/**).
PRODUCING = {*(("ingress", m) for m in ("put", "delete", "declare_queryable", "reply", "query", "liveliness_token")),
             ("egress", "query"), ("egress", "reply")}
# Grants of deploy/secure/profile.py that no interface uses: each serving identity may put and delete
# anywhere in its namespace gd2p/<S>/** (only the bridge publishes there: its state), the launcher has a
# worker's token and status spaces, and the planner may put on the command keys. Listed, so a new one fails.
UNUSED_GRANTS = {
    *((s, "ingress", m, f"gd2p/{s}/**") for s in ("generator", "validator", "sampler", "recorder", "launcher")
      for m in ("put", "delete")),
    *(("launcher", "ingress", m, "gd2p/status/launcher/**") for m in ("put", "delete")),
    ("launcher", "ingress", "liveliness_token", "gd2p/alive/launcher/**"),
    ("planner", "ingress", "put", "gd2p/robot_bridge/command/**"),
}


# ------------------------------------------------------------------------------ the registry and its sources
def test_every_key_of_keys_py_has_its_row():
    """A key space added to shared/bus/keys.py without a registry row fails here."""
    rows = {
        "PREFIX": lambda: interface(f"{keys.PREFIX}/robot_bridge/state"),
        "ALL_KEYS": lambda: interface(keys.ALL_KEYS),
        "ALIVE_PREFIX": lambda: interface(f"{keys.ALIVE_PREFIX}/planner/w-1"),
        "STATUS_PREFIX": lambda: interface(f"{keys.STATUS_PREFIX}/planner/w-1"),
        "LEASE_PREFIX": lambda: interface(f"{keys.LEASE_PREFIX}/client/cli/h-1"),
        "WATCHDOG_PREFIX": lambda: interface(f"{keys.WATCHDOG_PREFIX}/robot_bridge-1"),
        "CALLER_PREFIX": lambda: interface(f"{keys.CALLER_PREFIX}/c-1"),
        "caller_key": lambda: interface(keys.caller_key("c-1")),
        "ROBOT_COMMAND_KEY": lambda: interface(keys.ROBOT_COMMAND_KEY),
        "ROBOT_STATE_KEY": lambda: interface(keys.ROBOT_STATE_KEY),
        "ROBOT_ESTOP_KEY": lambda: interface(keys.ROBOT_ESTOP_KEY),
        "OBJECT_TRACK_KEY": lambda: interface(keys.OBJECT_TRACK_KEY),
        "PLANNER_DECISION_KEY": lambda: interface(keys.PLANNER_DECISION_KEY),
        "ROBOT_HELD_KEY": lambda: interface(keys.ROBOT_HELD_KEY),
        "ROBOT_CONFIRM_KEY": lambda: interface(keys.ROBOT_CONFIRM_KEY),
        "alive_key": lambda: interface(keys.alive_key("sampler", "w-1")),
        "alive_pattern": lambda: next(r for r in INTERFACES if r.pattern == keys.alive_pattern("sampler")),
        "job_key": lambda: interface(keys.job_key("sampler", "w-1")),
        "status_key": lambda: interface(keys.status_key("sampler", "w-1")),
        "status_pattern": lambda: next(r for r in INTERFACES if r.pattern == keys.status_pattern("sampler")),
    }
    defined = {name for name, value in vars(keys).items() if not name.startswith("_") and (
        isinstance(value, str) or (callable(value) and getattr(value, "__module__", None) == keys.__name__))}
    assert defined - {"check_chunk", "parse_alive_key"} == set(rows), "a key of keys.py has no row here"
    for name, row in rows.items():
        assert row().key.startswith(keys.PREFIX), name
    for svc in registry.SERVICES:
        assert interface(keys.job_key(svc, "w-1")).exchanges == next(w for w in WORKERS if w.name == svc).exchanges
        assert interface(keys.alive_key(svc, "w-1")).declarers == {svc} == interface(keys.status_key(svc, "w-1")).declarers
    for role in LEASE_ROLES:
        assert lease_key(role, "h-1") == lease_key(role, "h-1", registry.LEASE_HOLDERS[role][0])  # the default
        for identity in registry.LEASE_HOLDERS[role]:  # each identity holds only leases naming it
            assert interface(lease_key(role, "h-1", identity)).declarers == {identity}
        with pytest.raises(LookupError):
            interface(lease_key(role, "h-1", "validator"))
    assert interface(keys.ROBOT_COMMAND_KEY).callers == {"planner"}
    assert interface(keys.ROBOT_CONFIRM_KEY).callers == {"operator"}  # only the operator confirms
    with pytest.raises(LookupError):
        interface("gd2p/unknown/key")


def test_every_message_travels_on_some_key_and_the_documented_map_decodes():
    ours = {name for name, cls in MESSAGE_TYPES.items() if cls.__module__ == "shared.contracts.messages"}
    assert ours <= {m.__name__ for m in registry.message_types()}
    request = decode(msgpack.packb(registry.EXAMPLE_PUSH_REQUEST, use_bin_type=True), f"{ENCODING_PREFIX}PushRequest")
    assert isinstance(request, PushRequest) and request.object.library_id == "proc-box-013"
    assert (request.direction_deg, request.options.method, request.hand) == (90.0, "fixed", "allegro")


def test_the_committed_document_is_the_generated_one():
    committed = (ROOT / "docs" / "interfaces.md").read_text(encoding="utf-8")
    assert committed == registry.markdown(), f"docs/interfaces.md is stale: run `{registry.GENERATED_BY}`"
    out = subprocess.run([sys.executable, "-m", "shared.bus.interfaces", "--markdown"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120, check=True).stdout
    assert out == committed


def test_the_launcher_and_compose_run_the_registry_services():
    from deploy import launcher

    assert launcher.SERVICES == registry.SERVICES and launcher.SCALABLE == registry.SCALABLE
    assert interface(launcher.CONTROL_KEY).declarers == {"launcher"}
    compose = yaml.safe_load((ROOT / "deploy" / "docker-compose.yml").read_text())
    assert set(compose["services"]) == {"router", *registry.SERVICES}


@pytest.mark.parametrize("example", [EXAMPLE, TRACKER_EXAMPLE], ids=lambda p: p.name)
def test_the_examples_import_nothing_of_the_project(example):
    tree = ast.parse(example.read_text())
    imported = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    imported |= {node.module.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    assert imported - set(sys.stdlib_module_names) == {"zenoh", "msgpack"}


def test_the_tracker_examples_message_is_an_object_track_on_its_key():
    import importlib.util

    from shared.contracts.messages import ObjectTrack

    spec = importlib.util.spec_from_file_location("object_tracker", TRACKER_EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.KEY == keys.OBJECT_TRACK_KEY and module.ENCODING == f"{ENCODING_PREFIX}ObjectTrack"
    track = decode(msgpack.packb(module.track_message([0.5, 0.0, 0.04], [0.0, 0.0, 0.0, 1.0], "t"), use_bin_type=True),
                   module.ENCODING)
    assert isinstance(track, ObjectTrack) and track.pose.position == (0.5, 0.0, 0.04)


# ------------------------------------------------------------------------------ the access rules
def test_each_row_is_exactly_what_the_access_rules_allow():
    pytest.importorskip("cryptography")
    from deploy.secure import profile as acl
    from deploy.secure.certs import IDENTITIES

    assert set(registry.PARTICIPANTS) == set(IDENTITIES)
    assert set(registry.LEASE_HOLDERS) == set(LEASE_ROLES)
    wrong = {}
    for row in INTERFACES:
        for role, pairs in ROLE_MESSAGES[row.kind].items():
            for flow, message in pairs:
                allowed = acl.who_may(flow, message, row.sample_key())
                if allowed != getattr(row, role):
                    wrong[(row.key, role, flow, message)] = (sorted(allowed), sorted(getattr(row, role)))
    assert not wrong, f"(key, role, flow, message): (the rules allow, the registry says): {wrong}"


def test_the_access_rules_grant_nothing_the_registry_lacks():
    pytest.importorskip("cryptography")
    from deploy.secure import profile as acl
    from deploy.secure.certs import IDENTITIES

    config = acl.access_control()
    subjects: dict[str, set[str]] = {}
    for policy in config["policies"]:
        for rule_id in policy["rules"]:
            for subject in policy["subjects"]:
                subjects.setdefault(rule_id, set()).update(IDENTITIES if subject == acl.EVERYONE else {subject})
    granted = {(who, flow, message, key) for rule in config["rules"] for flow in rule["flows"]
               for message in rule["messages"] if (flow, message) in PRODUCING
               for key in rule["key_exprs"] for who in subjects[rule["id"]]}
    unused = {grant for grant in granted if not _used(*grant)}
    assert unused == UNUSED_GRANTS


def _used(who: str, flow: str, message: str, key: str) -> bool:
    """Does some row let `who` do `message` on a key the rule's `key` intersects? (a delete withdraws a put)"""
    pair = (flow, "put" if message == "delete" else message)
    return any(who in getattr(row, role) and pair in pairs and zenoh.KeyExpr(row.pattern).intersects(zenoh.KeyExpr(key))
               for row in INTERFACES for role, pairs in ROLE_MESSAGES[row.kind].items())


# ------------------------------------------------------------------------------ live
@pytest.fixture(scope="module")
def system(module_router, tmp_path_factory):
    """A worker of every service in this process (as tests/test_push.py's system, plus generator, sampler
    and recorder), registered on the router."""
    from services.generator import service as generator
    from services.planner import service as planner
    from services.robot_bridge import service as bridge
    from shared.bus import run_worker
    from shared.sampling import server as sampler
    from shared.validation import jobs as validator

    cfg = BusConfig(mode="client", connect=[module_router], connect_timeout_ms=5000)
    stop = threading.Event()
    workers = [
        threading.Thread(target=bridge.run, args=(cfg, "bridge-t", stop), daemon=True),
        threading.Thread(target=run_worker, args=(validator.SERVICE, validator.handlers(), cfg, "validator-t"),
                         kwargs={"stop": stop}, daemon=True),
        threading.Thread(target=planner.run, args=(cfg, "planner-t", stop, str(tmp_path_factory.mktemp("pushes"))),
                         daemon=True),
        threading.Thread(target=run_worker, args=(generator.SERVICE, generator.handlers(), cfg, "generator-t"),
                         kwargs={"stop": stop}, daemon=True),
        threading.Thread(target=run_worker, args=(sampler.SERVICE, sampler.handlers(), cfg, "sampler-t"),
                         kwargs={"stop": stop}, daemon=True),
        threading.Thread(target=_record, args=(cfg, tmp_path_factory.mktemp("recordings"), stop), daemon=True),
    ]
    for w in workers:
        w.start()
    with open_session(cfg) as session:
        deadline = time.monotonic() + 30.0
        while not set(registry.SERVICES) <= set(live := live_workers(session)):
            if time.monotonic() > deadline:
                pytest.fail(f"workers did not register: {live}")
            time.sleep(0.2)
    yield cfg, module_router
    stop.set()
    for w in workers:
        w.join(timeout=15.0)


def _record(cfg: BusConfig, record_dir: Path, stop: threading.Event) -> None:
    from services.recorder.service import RecorderService
    from visualisation.recorder import RotatingRecorder

    with open_session(cfg) as session:
        RecorderService(RotatingRecorder(record_dir)).run(session, worker_id="recorder-t", stop=stop)


class BusObserver:
    """Every publication (key, encoding) and liveliness token (key) seen under gd2p/** while open."""

    def __init__(self, session: zenoh.Session):
        self.samples: set[tuple[str, str]] = set()
        self.tokens: set[str] = set()
        self._lock = threading.Lock()
        self._subscribers = [session.declare_subscriber(keys.ALL_KEYS, self._on_sample),
                             session.liveliness().declare_subscriber(keys.ALL_KEYS, self._on_token, history=True)]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.samples.add((str(sample.key_expr), str(sample.encoding)))

    def _on_token(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.tokens.add(str(sample.key_expr))

    def close(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()


def test_the_raw_example_pushes_the_box_and_the_bus_carries_only_registered_traffic(system, tmp_path):
    cfg, endpoint = system
    with open_session(cfg) as session:
        observer = BusObserver(session)
        try:
            run = subprocess.run([sys.executable, str(EXAMPLE), "--connect", endpoint, "--timeout", "240"],
                                 cwd=tmp_path, capture_output=True, text=True, timeout=300)
            time.sleep(2.5)  # a status heartbeat of every worker
        finally:
            observer.close()
    assert run.returncode == 0, run.stdout + run.stderr
    assert "success: True" in run.stdout
    position = next(line for line in run.stdout.splitlines() if line.startswith("final object position:"))
    x, y, _ = (float(v) for v in position.split(":")[1].split())
    assert abs(x - 0.55) <= 0.03 and abs(y - 0.20) <= 0.03  # 0.20 m along +y (90°) from the default spot
    for key, encoding in observer.samples:
        row = interface(key, "publication")
        assert encoding == (f"{ENCODING_PREFIX}{row.message.__name__}" if row.message else "zenoh/bytes"), key
    for key in observer.tokens:
        interface(key, "liveliness")
    seen = {interface(key).title for key, _ in observer.samples} | {interface(key).title for key in observer.tokens}
    assert {"robot state", "planner lease", "router watchdog"} | {f"{s} status heartbeat" for s in registry.SERVICES} <= seen


def test_every_worker_accepts_exactly_its_rows_requests(system):
    cfg, _ = system
    with open_session(cfg) as session:
        assert {s.service for s in health(session)} == set(registry.SERVICES)  # HealthQuery -> WorkerStatus
        for svc in WORKERS:
            [worker_id] = live_workers(session, svc.name)[svc.name]
            reply = _ask(session, keys.job_key(svc.name, worker_id), ScaleRequest(service="validator", count=1))
            assert isinstance(reply, ErrorReply) and reply.code == "bad_request"
            accepts = reply.message.split(" accepts ", 1)[1].split("; got ")[0]
            expected = ", ".join(sorted(e.request.__name__ for e in svc.jobs)) or "only HealthQuery"
            assert accepts == expected, svc.name
        refusal = _ask(session, keys.ROBOT_COMMAND_KEY, HealthQuery())
        assert isinstance(refusal, ErrorReply) and refusal.code == "bad_request"
        assert [e.request.__name__ for e in interface(keys.ROBOT_COMMAND_KEY).exchanges] == ["ExecutionCommand"]
        assert "ExecutionCommand" in refusal.message


def _ask(session: zenoh.Session, key: str, message) -> object:
    payload, encoding = encode(message)
    [reply] = [r.ok for r in session.get(key, payload=payload, encoding=encoding, timeout=10.0) if r.ok is not None]
    return decode(reply.payload.to_bytes(), str(reply.encoding))

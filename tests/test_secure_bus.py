"""Who may do what on the bus: a router with mutual TLS and per-identity access control (deploy/secure).

A real bridge stack sits behind the command key: the safety Executor driving an xArm7 (fake controller at
the SDK boundary) + LEAP hand (Protocol 2.0 responder on a pty). Only the planner's certificate gets a
command through; another authenticated identity's command is dropped at the router; a session without
a client certificate cannot even connect.

Every other key space has an owner too (deploy/secure/profile.py): an attacker holding a valid
non-planner certificate cannot announce itself as a planner or answer a push, forge robot state,
worker status or a lease, nor reach the launcher's control key; the legitimate flows (the planner
dispatching to samplers and validators, the operator's tools calling the planner, heartbeats seen by
observers, the e-stop from anyone) still work. The certificate set keeps the CA key out of the
directory the processes read, and every key of shared/bus/keys.py has an owner in the rules.
"""
from __future__ import annotations

import contextlib
import stat
import struct
import threading
import time

import numpy as np
import pytest

pytest.importorskip("cryptography")
pytest.importorskip("xarm")
pytest.importorskip("dynamixel_sdk")

import zenoh

from conftest import free_port
from deploy.launcher import SERVICES, Launcher, LaunchError, request_scale
from deploy.secure import CertificateError, prepare
from deploy.secure import profile as acl
from deploy.secure.certs import IDENTITIES, generate
from services.robot_bridge.bus_safety import COMMAND_KEY, ESTOP_KEY, EStopSubscriber, LeasedExecutor
from shared.bus import (
    Dispatcher,
    RemoteError,
    Worker,
    health,
    keys,
    live_workers,
)
from shared.bus.lease import LEASE_ROLES, RouterWatchdog, lease_alive, lease_key
from shared.contracts.codec import decode, encode
from shared.contracts.errors import ServiceError
from shared.contracts.messages import (
    EStop,
    ExecutionCommand,
    ExecutionState,
    HealthQuery,
    ObjectRef,
    Plan,
    PushRequest,
    ScaleReply,
    WorkerStatus,
)
from shared.execution.executor import EStopLatch, Executor
from shared.execution.robots.leap.config import LeapConfig
from shared.execution.robots.leap.fake import DynamixelBus
from shared.execution.robots.leap.robot import LeapRobot
from shared.execution.robots.xarm7.config import XArm7Config
from shared.execution.robots.xarm7.fake import FakeXArmController, fake_xarm_api
from shared.execution.robots.xarm7.robot import XArm7Robot

HOME = np.array([0.0, -0.4, 0.0, 0.9, 0.0, 1.3, 0.0])
XARM7_JOINTS = tuple(f"joint{i}" for i in range(1, 8))  # the xArm7 URDF's
LEAP_JOINTS = tuple(str(i) for i in range(16))


@pytest.fixture(scope="module")
def secure(tmp_path_factory):
    """Certificates + configs, and the router running them on a free loopback port."""
    endpoint = f"tls/localhost:{free_port()}"
    profile = prepare(tmp_path_factory.mktemp("secure"), listen=[endpoint])
    router = zenoh.open(zenoh.Config.from_file(str(profile.router_config)))
    yield profile, endpoint
    router.close()


def session_as(profile, identity: str) -> zenoh.Session:
    cfg = zenoh.Config.from_file(str(profile.client_config(identity)))
    cfg.insert_json5("connect/timeout_ms", "5000")
    return zenoh.open(cfg)


@pytest.fixture(scope="module")
def bridge(secure):
    """The robot bridge, authenticated as robot_bridge, serving the command key with real safety checks."""
    profile, _ = secure
    session = session_as(profile, "robot_bridge")
    controller = FakeXArmController(initial_rad=HOME)
    bus = DynamixelBus(motor_ids=range(16))
    arm = XArm7Robot(XArm7Config("192.168.1.201"), api_factory=lambda ip: fake_xarm_api(controller, ip))
    hand = LeapRobot(LeapConfig(bus.port_name))
    arm.connect()
    hand.connect()
    estop = EStopSubscriber(session, EStopLatch())
    executor = LeasedExecutor(session, Executor("xarm7", "leap", [arm, hand], estop.latch))
    received: list[str] = []

    def answer(query: zenoh.Query) -> None:
        with query:  # finalised when done: the caller stops waiting
            command = decode(query.payload.to_bytes(), str(query.encoding), ExecutionCommand)
            received.append(command.id)
            payload, encoding = encode(executor.execute(command))
            query.reply(COMMAND_KEY, payload, encoding=encoding)

    def serve(query: zenoh.Query) -> None:  # never block Zenoh's callback thread: execute on a thread of its own
        threading.Thread(target=answer, args=(query,), daemon=True).start()

    queryable = session.declare_queryable(COMMAND_KEY, serve)
    # Puts on the command key (not how commands travel, but the ACL must stop them too) are recorded.
    listener = session.declare_subscriber(COMMAND_KEY, lambda sample: received.append(f"put:{sample.payload.to_bytes().decode()}"))
    yield controller, executor, received
    listener.undeclare()
    queryable.undeclare()
    estop.close()
    arm.disconnect()
    hand.disconnect()
    bus.close()
    session.close()


def command_from_here(controller: FakeXArmController, lease: str, duration_s: float = 0.3) -> ExecutionCommand:
    start = np.concatenate([controller.positions, np.zeros(16)])
    goal = start + np.concatenate([np.full(7, 0.05), np.zeros(16)])
    plan = Plan(arm="xarm7", hand="leap", joint_names=[*XARM7_JOINTS, *LEAP_JOINTS],
                positions=np.stack([start, goal]), times_s=np.array([0.0, duration_s]))
    return ExecutionCommand(plan=plan, lease_token=lease)


def send(session: zenoh.Session, command: ExecutionCommand, timeout: float = 3.0) -> list[ExecutionState]:
    payload, encoding = encode(command)
    replies = session.get(COMMAND_KEY, payload=payload, encoding=encoding, timeout=timeout)
    return [decode(r.ok.payload.to_bytes(), str(r.ok.encoding), ExecutionState) for r in replies if r.ok is not None]


def servo_commands(controller: FakeXArmController) -> int:
    return sum(1 for c in controller.commands if c[0] == "move_servoj")


def test_the_planner_identity_makes_the_robot_move(secure, bridge):
    profile, _ = secure
    controller, _, received = bridge
    with session_as(profile, "planner") as planner:
        lease = planner.liveliness().declare_token(lease_key("planner", "planner-1"))
        time.sleep(0.3)
        before = servo_commands(controller)
        command = command_from_here(controller, lease_key("planner", "planner-1"))
        states = send(planner, command)
        planner.put(COMMAND_KEY, b"from-planner")
        time.sleep(0.3)
        lease.undeclare()
    assert [s.status for s in states] == ["done"], [s.message for s in states]
    assert command.id in received and servo_commands(controller) > before
    assert "put:from-planner" in received


def test_the_lease_is_watched_through_the_access_rules(secure, bridge):
    profile, _ = secure
    controller, _, _ = bridge
    with session_as(profile, "planner") as planner:
        lease = planner.liveliness().declare_token(lease_key("planner", "planner-2"))
        time.sleep(0.3)
        command = command_from_here(controller, lease_key("planner", "planner-2"), duration_s=3.0)  # loses its lease on the way
        threading.Timer(0.6, lease.undeclare).start()
        t0 = time.monotonic()
        states = send(planner, command, timeout=6.0)
    assert [s.status for s in states] == ["stopped"] and "lease" in states[0].message
    assert time.monotonic() - t0 < 2.5


def test_another_identity_cannot_command_the_robot(secure, bridge):
    profile, _ = secure
    controller, _, received = bridge
    with session_as(profile, "validator") as intruder:
        lease = intruder.liveliness().declare_token(lease_key("planner", "validator-1"))
        time.sleep(0.3)
        before = servo_commands(controller)
        command = command_from_here(controller, lease_key("planner", "validator-1"))
        assert send(intruder, command, timeout=1.5) == []  # the router drops the query: no reply at all
        intruder.put(COMMAND_KEY, b"from-validator")  # nor does a put get through
        time.sleep(0.3)
        lease.undeclare()
    assert command.id not in received and servo_commands(controller) == before
    assert "put:from-validator" not in received


def test_only_the_operator_identity_may_release_a_held_plan(secure, bridge):
    """Issue 52 (`gd2p up --confirm`): the bridge holds the planner's command; a confirmation from cli, the
    planner or a validator is dropped by the router (no answer: ConfirmError) and the arm does not move; the
    operator's releases it."""
    from client.confirm import ConfirmError, confirm, held_plans
    from services.robot_bridge.bus_safety import ConfirmServer
    from shared.execution.confirm import ConfirmGate

    profile, _ = secure
    controller, executor, _ = bridge
    gate = ConfirmGate(executor.estop, timeout_s=30.0)
    with session_as(profile, "robot_bridge") as bridge_session:
        server = ConfirmServer(bridge_session, gate)
        executor.executor.hold = gate.hold
        try:
            with session_as(profile, "planner") as planner:
                token = planner.liveliness().declare_token(lease_key("planner", "planner-held"))
                time.sleep(0.3)
                before = servo_commands(controller)
                command = command_from_here(controller, lease_key("planner", "planner-held"))
                states: list[ExecutionState] = []
                sender = threading.Thread(target=lambda: states.extend(send(planner, command, timeout=40.0)),
                                          daemon=True)
                sender.start()
                deadline = time.monotonic() + 10.0
                while not gate.held() and time.monotonic() < deadline:
                    time.sleep(0.05)
                with session_as(profile, "cli") as cli:
                    assert [h.command_id for h in held_plans(cli)] == [command.id]  # anyone may see what waits
                for identity in ("cli", "planner", "validator"):
                    with session_as(profile, identity) as other:
                        with pytest.raises(ConfirmError, match="no robot bridge answered"):
                            confirm(other, command.id, operator=identity, timeout_s=1.0)
                assert servo_commands(controller) == before and [h.command_id for h in gate.held()] == [command.id]
                with session_as(profile, "operator") as operator:
                    reply = confirm(operator, command.id, operator="alice")
                sender.join(15.0)
                token.undeclare()
        finally:
            executor.executor.hold = None
            server.close()
    assert reply.accepted, reply.reason
    assert [s.status for s in states] == ["done"] and "confirmed by alice" in states[0].message, states
    assert servo_commands(controller) > before


def test_a_session_without_a_client_certificate_cannot_connect(secure):
    profile, endpoint = secure
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", f'["{endpoint}"]')
    cfg.insert_json5("connect/timeout_ms", "1000")
    cfg.insert_json5("transport/link/tls/root_ca_certificate", f'"{profile.directory / "ca.pem"}"')
    with pytest.raises(zenoh.ZError):
        zenoh.open(cfg)
    plain = zenoh.Config()  # nor over plain TCP: the secure router listens on TLS only
    plain.insert_json5("mode", '"client"')
    plain.insert_json5("connect/endpoints", f'["{endpoint.replace("tls/", "tcp/")}"]')
    plain.insert_json5("connect/timeout_ms", "1000")
    with pytest.raises(zenoh.ZError):
        zenoh.open(plain)


# ------------------------------------------------------------------------------ helpers of the ACL tests
def tokens(session: zenoh.Session, pattern: str, timeout: float = 1.5) -> set[str]:
    """The liveliness tokens the router reports on `pattern` to this session."""
    return {str(r.ok.key_expr) for r in session.liveliness().get(pattern, timeout=timeout) if r.ok is not None}


class Collector:
    """Every key published on `pattern` that reaches `session` (a subscriber, as an observer has)."""

    def __init__(self, session: zenoh.Session, pattern: str):
        self.keys: list[str] = []
        self._subscriber = session.declare_subscriber(pattern, lambda sample: self.keys.append(str(sample.key_expr)))

    def wait_for(self, key: str, timeout: float = 2.0) -> bool:
        deadline = time.monotonic() + timeout
        while key not in self.keys and time.monotonic() < deadline:
            time.sleep(0.02)
        return key in self.keys

    def close(self) -> None:
        self._subscriber.undeclare()


@contextlib.contextmanager
def serving(session: zenoh.Session, service: str, worker_id: str, handlers=None):
    """A real `Worker` of `service` on `session` (token, queryable, status heartbeat) for the block."""
    worker = Worker(service, handlers or {}, session=session, worker_id=worker_id, status_period_s=0.2,
                    drain_timeout_s=1.0)
    thread = threading.Thread(target=worker.run, name=f"test-{worker_id}", daemon=True)
    thread.start()
    try:
        yield worker
    finally:
        worker.stop()
        thread.join(timeout=5.0)


def push_request() -> PushRequest:
    return PushRequest(object=ObjectRef(library_id="proc-box-013"), direction_deg=90.0, distance_m=0.2)


def planner_refuses(request: PushRequest):
    raise ServiceError("infeasible", "the real planner answered")


# ------------------------------------------------------------------------------ attacks and legitimate flows
def test_only_the_planner_identity_can_announce_a_planner_and_answer_a_push(secure):
    """A validator certificate declaring a planner token and worker queryable (and a catch-all queryable)
    gets no query: a push-style call from cli finds no planner; the real planner then answers it."""
    profile, _ = secure
    forged_queries: list[str] = []

    def forge(query: zenoh.Query) -> None:
        forged_queries.append(str(query.key_expr))
        query.reply(query.key_expr, b"SUCCESS")

    with session_as(profile, "validator") as intruder, session_as(profile, "cli") as operator:
        token = intruder.liveliness().declare_token(keys.alive_key("planner", "forged-1"))
        forged = intruder.declare_queryable(keys.job_key("planner", "forged-1"), forge)
        catch_all = intruder.declare_queryable("gd2p/**", forge)
        time.sleep(0.4)
        assert tokens(operator, keys.alive_pattern("planner")) == set()
        payload, encoding = encode(push_request())
        direct = [r for r in operator.get(keys.job_key("planner", "forged-1"), payload=payload, encoding=encoding,
                                          timeout=1.0) if r.ok is not None]
        assert direct == []
        with Dispatcher(operator, "planner", timeout_s=1.0, max_attempts=1) as planners:
            with pytest.raises(TimeoutError):
                planners.call(push_request(), timeout=1.5)  # no live planner at all: nothing to forge a reply
        assert forged_queries == []

        with session_as(profile, "planner") as planner, serving(planner, "planner", "planner-1",
                                                                {PushRequest: planner_refuses}):
            with Dispatcher(operator, "planner", timeout_s=5.0, max_attempts=1) as planners:
                with pytest.raises(RemoteError) as answered:
                    planners.call(push_request(), timeout=10.0)
                assert planners.live() == ["planner-1"]
        assert answered.value.code == "infeasible" and answered.value.message == "the real planner answered"
        assert forged_queries == []
        catch_all.undeclare()
        forged.undeclare()
        token.undeclare()


def test_the_planner_dispatches_to_samplers_and_validators_and_only_callers_reach_a_worker(secure):
    profile, _ = secure
    with session_as(profile, "sampler") as sampler, session_as(profile, "validator") as validator, \
            session_as(profile, "planner") as planner, session_as(profile, "generator") as generator, \
            serving(sampler, "sampler", "sampler-1"), serving(validator, "validator", "validator-1"):
        for service in ("sampler", "validator"):
            with Dispatcher(planner, service, timeout_s=5.0) as workers:
                status = workers.call(HealthQuery(), timeout=10.0)
            assert isinstance(status, WorkerStatus) and status.worker_id == f"{service}-1"
        # A worker asks itself (its container healthcheck runs under its own identity).
        assert [s.worker_id for s in health(sampler, "sampler", timeout=2.0)] == ["sampler-1"]
        # Not a caller of the sampler: the validator and the generator get nothing from it.
        assert health(validator, "sampler", timeout=1.0) == []
        assert health(generator, "sampler", timeout=1.0) == []
        assert health(generator, "validator", timeout=1.0) == []


def test_each_service_heartbeat_and_token_reach_observers_and_nobody_forges_them(secure):
    profile, _ = secure
    with contextlib.ExitStack() as stack:
        observer = stack.enter_context(session_as(profile, "cli"))
        statuses = Collector(observer, "gd2p/status/**")
        for service in SERVICES:
            stack.enter_context(serving(stack.enter_context(session_as(profile, service)), service, f"{service}-t"))
        intruder = stack.enter_context(session_as(profile, "validator"))
        intruder_token = intruder.liveliness().declare_token(keys.alive_key("planner", "fake"))
        for service in SERVICES:
            assert statuses.wait_for(keys.status_key(service, f"{service}-t")), service
        intruder.put(keys.status_key("planner", "fake"), b"forged")
        intruder.put(keys.status_key("robot_bridge", "fake"), b"forged")
        time.sleep(0.5)
        live = live_workers(observer, timeout=2.0)
        statuses.close()
        intruder_token.undeclare()
    assert {svc: ids for svc, ids in live.items()} == {svc: [f"{svc}-t"] for svc in SERVICES}
    assert not any(key.endswith("/fake") for key in statuses.keys)


def test_robot_state_is_published_by_the_robot_bridge_only(secure):
    profile, _ = secure
    with session_as(profile, "planner") as planner, session_as(profile, "validator") as validator, \
            session_as(profile, "cli") as operator, session_as(profile, "robot_bridge") as bridge_session, \
            session_as(profile, "recorder") as recorder:
        states = Collector(recorder, keys.ROBOT_STATE_KEY)  # an observer of the robot's state
        time.sleep(0.3)
        for forger in (validator, operator, planner):
            forger.put(keys.ROBOT_STATE_KEY, b"forged")
        time.sleep(0.5)
        assert states.keys == []
        bridge_session.put(keys.ROBOT_STATE_KEY, b"real")
        assert states.wait_for(keys.ROBOT_STATE_KEY)
        states.close()
    assert states.keys == [keys.ROBOT_STATE_KEY]


def test_only_the_bridge_identity_beats_on_the_router_watchdog_key(secure):
    """Issue 53: a beat numbered 2^64-1 on the watchdog's key once hid a frozen router. Under the secure
    profile a cli or validator certificate cannot put there at all: the bridge's watchdog (both sessions
    CN robot_bridge) hears its own beats and nothing of the forgers'; a put by the bridge's identity
    gets through (and is ignored by the watchdog as not its own beat)."""
    profile, _ = secure
    with session_as(profile, "robot_bridge") as bridge_session, session_as(profile, "robot_bridge") as probe, \
            session_as(profile, "cli") as operator, session_as(profile, "validator") as validator:
        watchdog = RouterWatchdog(bridge_session, probe, f"robot_bridge-{bridge_session.zid()}")
        try:
            time.sleep(0.4)
            forged = struct.pack("!Q", 2**64 - 1)
            for forger in (operator, validator):
                for _ in range(3):
                    forger.put(watchdog.key, forged)
            time.sleep(0.5)
            assert watchdog.silence_s() < watchdog.bound_s  # the bridge's own beats pass the access rules
            assert not watchdog.ignored, watchdog.ignored  # the forgers' never reached it
            probe.put(watchdog.key, forged)  # the bridge's identity may put (and the watchdog still ignores it)
            deadline = time.monotonic() + 2.0
            while not watchdog.ignored and time.monotonic() < deadline:
                watchdog.silence_s()
                time.sleep(0.02)
            assert watchdog.ignored == {"length": 1}
        finally:
            watchdog.close()


def test_a_lease_token_is_declared_only_by_the_identity_of_its_role(secure):
    profile, _ = secure
    with session_as(profile, "planner") as planner, session_as(profile, "cli") as operator, \
            session_as(profile, "validator") as validator, session_as(profile, "robot_bridge") as bridge_session:
        forged = [validator.liveliness().declare_token(lease_key("planner", "validator-1")),
                  operator.liveliness().declare_token(lease_key("planner", "cli-1")),
                  validator.liveliness().declare_token(lease_key("client", "validator-1")),
                  planner.liveliness().declare_token(lease_key("client", "planner-1"))]
        real = [planner.liveliness().declare_token(lease_key("planner", "planner-1")),
                operator.liveliness().declare_token(lease_key("client", "cli-1"))]
        time.sleep(0.4)
        # The bridge checks the planner's lease; the planner watches the push client's.
        assert lease_alive(bridge_session, lease_key("planner", "planner-1"))
        assert lease_alive(planner, lease_key("client", "cli-1"))
        for key in (lease_key("planner", "validator-1"), lease_key("planner", "cli-1")):
            assert not lease_alive(bridge_session, key, timeout_s=0.5), key
        assert not lease_alive(planner, lease_key("client", "validator-1"), timeout_s=0.5)
        # (a session sees its own tokens without the router: ask another session about the planner's)
        assert not lease_alive(bridge_session, lease_key("client", "planner-1"), timeout_s=0.5)
        assert tokens(bridge_session, "gd2p/lease/**") == {lease_key("planner", "planner-1"), lease_key("client", "cli-1")}
        for token in forged + real:
            token.undeclare()


def test_a_lease_key_names_its_holder_and_only_that_identity_may_hold_it(secure):
    """Issue 53: a `cli` certificate could hold any client's lease. A lease key now names its holder's
    identity (gd2p/lease/<role>/<identity>/<holder>) and an identity may declare tokens only under its
    own part, for a role it may hold: cli holds gd2p/lease/client/cli/*, and neither another identity's
    client lease nor a planner lease (under the planner's part or its own)."""
    profile, _ = secure
    for key in (lease_key("client", "x", "operator"), lease_key("client", "x", "validator"),
                lease_key("planner", "x", "cli"), lease_key("planner", "x"), f"{lease_key('client', 'x')}/deeper"):
        assert "cli" not in acl.who_may("ingress", "liveliness_token", key), key
    assert acl.who_may("ingress", "liveliness_token", lease_key("client", "x", "operator")) == frozenset()
    assert acl.who_may("ingress", "liveliness_token", lease_key("client", "x")) == {"cli"}
    with session_as(profile, "cli") as operator, session_as(profile, "planner") as planner:
        others = [lease_key("client", "cli-1", "operator"), lease_key("client", "cli-2", "validator"),
                  lease_key("planner", "cli-3", "cli"), lease_key("planner", "cli-4")]
        own = lease_key("client", "cli-5")
        declared = [operator.liveliness().declare_token(key) for key in (*others, own)]
        time.sleep(0.4)
        assert lease_alive(planner, own)  # the planner watches the push client's lease
        for key in others:  # (a session sees its own tokens without the router: ask another session)
            assert not lease_alive(planner, key, timeout_s=0.5), key
        assert tokens(planner, "gd2p/lease/**") == {own}
        for token in declared:
            token.undeclare()


def test_the_estop_stays_open_to_every_identity(secure, bridge):
    profile, _ = secure
    _, executor, _ = bridge
    for identity in ("cli", "validator"):
        with session_as(profile, identity) as anyone:
            time.sleep(0.2)
            payload, encoding = encode(EStop(reason=f"secure e-stop from {identity}", issued_by=identity))
            anyone.put(ESTOP_KEY, payload, encoding=encoding)  # stopping must never need the planner
            deadline = time.monotonic() + 2.0
            while not executor.estop.triggered.is_set() and time.monotonic() < deadline:
                time.sleep(0.05)
        assert executor.estop.triggered.is_set() and executor.estop.last.reason == f"secure e-stop from {identity}"
        executor.estop.reset()


def test_only_the_operator_identity_reaches_the_launcher_control_key(secure):
    """A launcher joining as a client (CN launcher) serves the control key; only CN operator's scale
    request reaches it: cli, validator and planner certificates get no answer at all."""
    profile, _ = secure
    served: list[str] = []

    def serve(query: zenoh.Query) -> None:
        with query:
            served.append(query.payload.to_bytes().decode(errors="replace"))
            payload, encoding = encode(ScaleReply(service="planner", count=0))
            query.reply(query.key_expr, payload, encoding=encoding)

    with session_as(profile, "launcher") as launcher_session:
        control = launcher_session.declare_queryable("gd2p/launcher/control", serve)
        time.sleep(0.3)
        for identity in ("cli", "validator", "planner"):
            with session_as(profile, identity) as intruder:
                with pytest.raises(LaunchError, match="no launcher answered"):
                    request_scale(intruder, "planner", 0, timeout=1.0)
        assert served == []
        with session_as(profile, "operator") as operator:
            assert request_scale(operator, "planner", 0, timeout=5.0).count == 0
        assert len(served) == 1
        control.undeclare()


def test_gd2p_up_secure_serves_scaling_to_the_operator_only_and_within_its_limit(tmp_path):
    """The local launcher's own router (it serves the control key itself) under the secure profile."""
    launcher = Launcher(validators=0, listen=f"tls/localhost:{free_port()}", record_dir=tmp_path / "rec",
                        log_dir=tmp_path / "logs", secure_dir=tmp_path / "secure", max_scale={"planner": 1})
    launcher.initial_counts = {}  # no service processes: only the router and its control key
    launcher.start()
    try:
        with session_as(launcher.secure, "cli") as operator_tools:
            with pytest.raises(LaunchError, match="no launcher answered"):
                request_scale(operator_tools, "planner", 0, timeout=1.5)
        with session_as(launcher.secure, "operator") as operator:
            assert request_scale(operator, "planner", 0, timeout=10.0).count == 0
            with pytest.raises(RemoteError) as refused:
                request_scale(operator, "planner", 2, timeout=10.0)
        assert refused.value.code == "bad_request" and "maximum on this launcher is 1" in refused.value.message
        assert launcher.children() == []
    finally:
        launcher.stop()


# ------------------------------------------------------------------------------ the rules, offline
ALL = frozenset(IDENTITIES)
# Who may query each service's worker keys (jobs and health queries): the spec the rules must meet.
QUERIERS = {
    "planner": {"planner", "cli"},
    "generator": {"generator", "cli"},
    "validator": {"validator", "planner", "cli"},
    "sampler": {"sampler", "planner", "cli"},
    "robot_bridge": {"robot_bridge", "cli"},
    "recorder": {"recorder", "cli"},
}
HELPERS = {"check_chunk", "parse_alive_key"}  # names of shared/bus/keys.py that make no key


def key_space_expectations() -> dict[str, list[tuple[str, str, str, frozenset[str]]]]:
    """Name in shared/bus/keys.py -> (flow, message, key, identities the router must allow) rows."""
    w = acl.WORKER_IDENTITIES
    sample_rows = [("ingress", "declare_subscriber", keys.ALL_KEYS, ALL)]
    return {
        "PREFIX": [("ingress", m, f"{keys.PREFIX}/unowned/key", frozenset())
                   for m in ("put", "declare_queryable", "reply", "query", "liveliness_token")],
        "ALL_KEYS": sample_rows + [("ingress", "declare_liveliness_subscriber", keys.ALL_KEYS, ALL),
                                   ("ingress", "liveliness_query", keys.ALL_KEYS, ALL),
                                   ("egress", "put", keys.ALL_KEYS, ALL),
                                   ("ingress", "put", keys.ALL_KEYS, frozenset())],
        "ALIVE_PREFIX": [("ingress", "liveliness_token", f"{keys.ALIVE_PREFIX}/**", frozenset())],
        "alive_key": [("ingress", "liveliness_token", keys.alive_key(s, "w-1"), frozenset({s})) for s in w],
        "alive_pattern": [("ingress", "liveliness_query", keys.alive_pattern(s), ALL) for s in (*w, None)]
                         + [("ingress", "declare_liveliness_subscriber", keys.alive_pattern(s), ALL) for s in w],
        "job_key": [row for s in w for row in (
            ("ingress", "declare_queryable", keys.job_key(s, "w-1"), frozenset({s})),
            ("ingress", "reply", keys.job_key(s, "w-1"), frozenset({s})),
            ("egress", "query", keys.job_key(s, "w-1"), frozenset({s})),
            ("ingress", "query", keys.job_key(s, "w-1"), frozenset(QUERIERS[s])),
            ("egress", "reply", keys.job_key(s, "w-1"), frozenset(QUERIERS[s])),
            ("ingress", "query", f"{keys.PREFIX}/{s}/worker/*/job", frozenset(QUERIERS[s])),  # gd2p health
        )],
        "STATUS_PREFIX": [("ingress", "put", f"{keys.STATUS_PREFIX}/**", frozenset())],
        "status_key": [("ingress", "put", keys.status_key(s, "w-1"), frozenset({s})) for s in w],
        "status_pattern": [("ingress", "declare_subscriber", keys.status_pattern(s), ALL) for s in (*w, None)],
        "ROBOT_COMMAND_KEY": [
            ("ingress", "query", keys.ROBOT_COMMAND_KEY, frozenset({"planner"})),
            ("ingress", "put", keys.ROBOT_COMMAND_KEY, frozenset({"planner", "robot_bridge"})),
            ("egress", "query", keys.ROBOT_COMMAND_KEY, frozenset({"robot_bridge"})),
            ("ingress", "declare_queryable", keys.ROBOT_COMMAND_KEY, frozenset({"robot_bridge"})),
            ("ingress", "reply", keys.ROBOT_COMMAND_KEY, frozenset({"robot_bridge"})),
            ("egress", "reply", keys.ROBOT_COMMAND_KEY, frozenset({"planner"})),
        ],
        "ROBOT_STATE_KEY": [("ingress", "put", keys.ROBOT_STATE_KEY, frozenset({"robot_bridge"})),
                            ("ingress", "declare_subscriber", keys.ROBOT_STATE_KEY, ALL)],
        "OBJECT_TRACK_KEY": [("ingress", "put", keys.OBJECT_TRACK_KEY, frozenset({"robot_bridge", "tracker"})),
                             ("ingress", "declare_subscriber", keys.OBJECT_TRACK_KEY, ALL)],
        # The live view's push decisions: in the planner's namespace, so only the planner publishes them.
        "PLANNER_DECISION_KEY": [("ingress", "put", keys.PLANNER_DECISION_KEY, frozenset({"planner"})),
                                 ("ingress", "declare_subscriber", keys.PLANNER_DECISION_KEY, ALL)],
        # Preview and confirm: the bridge publishes held plans; only the operator confirms.
        "ROBOT_HELD_KEY": [("ingress", "put", keys.ROBOT_HELD_KEY, frozenset({"robot_bridge"})),
                           ("ingress", "declare_subscriber", keys.ROBOT_HELD_KEY, ALL)],
        "ROBOT_CONFIRM_KEY": [("ingress", "query", keys.ROBOT_CONFIRM_KEY, frozenset({"operator"})),
                              ("egress", "reply", keys.ROBOT_CONFIRM_KEY, frozenset({"operator"})),
                              ("ingress", "declare_queryable", keys.ROBOT_CONFIRM_KEY, frozenset({"robot_bridge"})),
                              ("egress", "query", keys.ROBOT_CONFIRM_KEY, frozenset({"robot_bridge"}))],
        "ROBOT_ESTOP_KEY": [("ingress", "put", keys.ROBOT_ESTOP_KEY, ALL),
                            ("egress", "put", keys.ROBOT_ESTOP_KEY, ALL)],
        # Router watchdog beats (shared/bus/lease.py): the bridge's own (issue 53), see profile.WATCHDOG_BEATERS.
        "WATCHDOG_PREFIX": [("ingress", "put", f"{keys.WATCHDOG_PREFIX}/w-1", frozenset({"robot_bridge"})),
                            ("egress", "put", f"{keys.WATCHDOG_PREFIX}/w-1", ALL),
                            ("ingress", "declare_subscriber", f"{keys.WATCHDOG_PREFIX}/w-1", ALL),
                            ("ingress", "declare_queryable", f"{keys.WATCHDOG_PREFIX}/w-1", frozenset()),
                            ("ingress", "liveliness_token", f"{keys.WATCHDOG_PREFIX}/w-1", frozenset())],
        # A Dispatcher's presence (shared/bus/worker.py Callers): any identity may declare one (it only keeps its
        # own jobs from being cancelled early), nobody may put or serve there.
        "CALLER_PREFIX": [("ingress", "liveliness_token", f"{keys.CALLER_PREFIX}/c-1", ALL),
                          ("ingress", "put", f"{keys.CALLER_PREFIX}/c-1", frozenset()),
                          ("ingress", "declare_queryable", f"{keys.CALLER_PREFIX}/c-1", frozenset())],
        "caller_key": [("ingress", "liveliness_token", keys.caller_key("c-1"), ALL),
                       ("ingress", "declare_liveliness_subscriber", keys.caller_key("c-1"), ALL)],
        "LEASE_PREFIX": [("ingress", "liveliness_token", lease_key(role, "h-1", holder), frozenset({holder}))
                         for role, holder in (("planner", "planner"), ("client", "cli"))]
                        + [("ingress", "liveliness_token", f"{keys.LEASE_PREFIX}/h-1", frozenset()),
                           ("ingress", "liveliness_query", lease_key("planner", "h-1"), ALL),
                           ("ingress", "declare_liveliness_subscriber", lease_key("client", "h-1"), ALL)],
    }


def test_every_key_of_the_bus_has_an_owner_in_the_access_rules():
    """Each key space of shared/bus/keys.py (plus the leases and the launcher's control key) is open
    exactly to its owners: a new key must be added here and to profile.py, or this test fails; no
    key is writable by everyone but the e-stop (and tokens by everyone only on the callers' presence key), and every
    concrete key has someone who may write it."""
    from deploy.launcher import CONTROL_KEY

    expectations = key_space_expectations()
    defined = {name for name, value in vars(keys).items() if not name.startswith("_") and (
        isinstance(value, str) or (callable(value) and getattr(value, "__module__", None) == keys.__name__))}
    unknown = defined - set(expectations) - HELPERS
    assert not unknown, (f"shared/bus/keys.py defines {sorted(unknown)}: give each an owner in "
                         f"deploy/secure/profile.py and a row in key_space_expectations()")
    assert set(acl.WORKER_IDENTITIES) == set(SERVICES) == set(QUERIERS)  # a new service needs its key spaces
    assert set(acl.LEASE_HOLDERS) == set(LEASE_ROLES)  # a new lease role needs its holder
    rows = [row for name in sorted(expectations) for row in expectations[name]]
    rows += [("ingress", "query", CONTROL_KEY, frozenset({"operator"})),
             ("egress", "reply", CONTROL_KEY, frozenset({"operator"})),
             ("ingress", "declare_queryable", CONTROL_KEY, frozenset({"launcher"})),
             ("egress", "query", CONTROL_KEY, frozenset({"launcher"}))]
    wrong = {(flow, message, key): (sorted(acl.who_may(flow, message, key)), sorted(expected))
             for flow, message, key, expected in rows if acl.who_may(flow, message, key) != expected}
    assert not wrong, f"(flow, message, key): (allowed, expected): {wrong}"

    producing = ("put", "delete", "declare_queryable", "reply", "liveliness_token", "query")
    concrete = {key for _, _, key, _ in rows if "*" not in key and "/unowned/" not in key
                and key != f"{keys.LEASE_PREFIX}/h-1"}
    for key in concrete:
        writers = set().union(*(acl.who_may("ingress", m, key) for m in producing))
        assert writers, f"{key}: nobody may write, serve or query it (silently denied)"
        open_put = any(zenoh.KeyExpr(o).includes(zenoh.KeyExpr(key)) for o in acl.OPEN_PUT_KEYS)
        open_token = any(zenoh.KeyExpr(o).includes(zenoh.KeyExpr(key)) for o in acl.OPEN_TOKEN_KEYS)
        for message in producing:
            if not (open_put and message == "put") and not (open_token and message == "liveliness_token"):
                assert acl.who_may("ingress", message, key) != ALL, f"{key}: everyone may {message} (silently open)"


def test_the_router_config_carries_the_rules_zenoh_accepts(secure):
    profile, _ = secure
    config = zenoh.Config.from_file(str(profile.router_config))
    assert config.get_json("access_control/default_permission") == '"deny"'
    assert config.get_json("transport/link/tls/enable_mtls") == "true"
    subjects = {s["id"]: s.get("cert_common_names") for s in acl.access_control()["subjects"]}
    assert subjects[acl.EVERYONE] is None and all(subjects[i] == [i] for i in subjects if i != acl.EVERYONE)


# ------------------------------------------------------------------------------ the certificate set
def test_the_ca_key_is_kept_out_of_the_directory_the_processes_read(tmp_path, capsys):
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    from deploy.secure.__main__ import main

    out = tmp_path / "generated"
    argv = ["--out", str(out), "--connect", "tls/router:7447", "--mounted-at", "/secure"]
    assert main(argv) == 0
    ca_key = tmp_path / "generated-ca" / "ca.key"
    assert str(ca_key) in capsys.readouterr().out
    assert not (out / "ca.key").exists() and ca_key.is_file()
    assert stat.S_IMODE(ca_key.stat().st_mode) == 0o600 and stat.S_IMODE(ca_key.parent.stat().st_mode) == 0o700
    ca_public = x509.load_pem_x509_certificate((out / "ca.pem").read_bytes()).public_key()
    assert serialization.load_pem_private_key(ca_key.read_bytes(), None).public_key() == ca_public
    for key_file in out.glob("*.key"):  # every key in the directory is a leaf's, none is the CA's
        assert serialization.load_pem_private_key(key_file.read_bytes(), None).public_key() != ca_public, key_file
    assert {p.name for p in out.glob("*.key")} == {f"{i}.key" for i in (*IDENTITIES, "router")}

    with pytest.raises(CertificateError, match="must not be kept in"):
        generate(tmp_path / "inside", ca_dir=tmp_path / "inside" / "ca")
    with pytest.raises(CertificateError, match="exists already"):  # never overwrite another set's CA key
        generate(tmp_path / "other", ca_dir=ca_key.parent)
    (out / "ca.key").write_bytes(ca_key.read_bytes())  # the old layout: CA key beside the certificates
    with pytest.raises(CertificateError, match="must not sit in the directory"):
        prepare(out, ["tls/0.0.0.0:7447"])
    assert main(argv) == 1 and "must not sit in the directory" in capsys.readouterr().err


def test_an_identity_added_later_is_issued_from_the_offline_ca(tmp_path):
    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric import ec

    directory = tmp_path / "secure"
    prepare(directory, ["tls/localhost:7447"])
    for suffix in (".pem", ".key"):  # a set generated before the "operator" identity existed
        (directory / f"operator{suffix}").unlink()
    (directory / "client-operator.json5").unlink()
    ca_dir = directory.with_name("secure-ca")
    ca_dir.rename(tmp_path / "offline")
    with pytest.raises(CertificateError, match="CA key"):
        prepare(directory, ["tls/localhost:7447"])
    (tmp_path / "offline").rename(ca_dir)
    profile = prepare(directory, ["tls/localhost:7447"])
    cert = x509.load_pem_x509_certificate((directory / "operator.pem").read_bytes())
    ca = x509.load_pem_x509_certificate((directory / "ca.pem").read_bytes())
    ca.public_key().verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm))
    assert cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)[0].value == "operator"
    assert profile.client_config("operator").is_file()


def test_the_launcher_gives_each_service_only_its_own_identity(tmp_path):
    launcher = Launcher(validators=0, listen=f"tls/localhost:{free_port()}", record_dir=tmp_path / "rec",
                        log_dir=tmp_path / "logs", secure_dir=tmp_path / "secure")
    for service in SERVICES:
        command = launcher._command(service, f"{service}-1")
        configs = [command[i + 1] for i, arg in enumerate(command) if arg == "--zenoh-config"]
        assert configs == [str(launcher.secure.client_config(service))]
        config = zenoh.Config.from_file(configs[0])
        assert config.get_json("transport/link/tls/connect_certificate") == f'"{tmp_path / "secure" / service}.pem"'
        assert config.get_json("transport/link/tls/connect_private_key") == f'"{tmp_path / "secure" / service}.key"'


@pytest.mark.slow  # spawns every service process (~10 s on a loaded 2-core machine)
def test_gd2p_up_secure_brings_every_service_up_over_mutual_tls(tmp_path):
    """The local launcher's secure profile: each service joins with its own certificate, through the ACL."""
    from deploy.launcher import Launcher

    launcher = Launcher(validators=0, listen=f"tls/localhost:{free_port()}", record_dir=tmp_path / "rec",
                        log_dir=tmp_path / "logs", secure_dir=tmp_path / "secure")
    launcher.start()
    try:
        workers = launcher.wait_ready(90)
        assert all(workers[s] for s in ("planner", "robot_bridge", "recorder"))
        with session_as(launcher.secure, "cli") as operator:  # `gd2p status --zenoh-config .../client-cli.json5`
            alive = {str(r.ok.key_expr) for r in operator.liveliness().get("gd2p/alive/*/*", timeout=2.0) if r.ok}
            # `gd2p health --service S`: every real service serves its worker key under its own identity
            answered = {svc: [s.worker_id for s in health(operator, svc, timeout=5.0)] for svc in workers}
        assert "gd2p/alive/robot_bridge/robot_bridge-1" in alive
        assert answered == {svc: ids for svc, ids in workers.items()}
    finally:
        launcher.stop()

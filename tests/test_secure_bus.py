"""Who may command the robot: a router with mutual TLS and access control (deploy/secure).

A real bridge stack sits behind the command key: a SafeExecutor driving an xArm7 (fake controller at
the SDK boundary) + LEAP hand (Protocol 2.0 responder on a pty). Only the planner's certificate gets a
command through; another authenticated identity's command is dropped at the router; a session without
a client certificate cannot even connect. The ordinary bus and the e-stop stay open to everyone.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

pytest.importorskip("cryptography")
pytest.importorskip("xarm")
pytest.importorskip("dynamixel_sdk")

import zenoh  # noqa: E402

from deploy.secure import prepare  # noqa: E402
from services.robot_bridge.adapters.leap import LeapBackend  # noqa: E402
from services.robot_bridge.adapters.xarm import XArmBackend  # noqa: E402
from services.robot_bridge.devsim.dynamixel import DynamixelBus  # noqa: E402
from services.robot_bridge.devsim.xarm import FakeXArmController, fake_xarm_api  # noqa: E402
from services.robot_bridge.safety import (  # noqa: E402
    COMMAND_KEY,
    ESTOP_KEY,
    LEAP_LIMITS,
    XARM7_LIMITS,
    Device,
    SafeExecutor,
)
from shared.codec import decode, encode  # noqa: E402
from shared.messages import EStop, ExecutionCommand, ExecutionState, Plan  # noqa: E402
from conftest import free_port  # noqa: E402

HOME = np.array([0.0, -0.4, 0.0, 0.9, 0.0, 1.3, 0.0])


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
    arm = XArmBackend("192.168.1.201", api_factory=lambda ip: fake_xarm_api(controller, ip))
    hand = LeapBackend(bus.port_name)
    arm.connect()
    hand.connect()
    executor = SafeExecutor(session, "xarm7", "leap", [Device(arm, XARM7_LIMITS), Device(hand, LEAP_LIMITS)])
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
    executor.close()
    arm.disconnect()
    hand.disconnect()
    bus.close()
    session.close()


def command_from_here(controller: FakeXArmController, lease: str, duration_s: float = 0.3) -> ExecutionCommand:
    start = np.concatenate([controller.positions, np.zeros(16)])
    goal = start + np.concatenate([np.full(7, 0.05), np.zeros(16)])
    plan = Plan(arm="xarm7", hand="leap", joint_names=[*XARM7_LIMITS.joint_names, *LEAP_LIMITS.joint_names],
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
        lease = planner.liveliness().declare_token("gd2p/lease/planner-1")  # dropping the token undeclares it
        time.sleep(0.3)
        before = servo_commands(controller)
        command = command_from_here(controller, "gd2p/lease/planner-1")
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
        lease = planner.liveliness().declare_token("gd2p/lease/planner-2")
        time.sleep(0.3)
        command = command_from_here(controller, "gd2p/lease/planner-2", duration_s=3.0)  # loses its lease on the way
        threading.Timer(0.6, lease.undeclare).start()
        t0 = time.monotonic()
        states = send(planner, command, timeout=6.0)
    assert [s.status for s in states] == ["stopped"] and "lease" in states[0].message
    assert time.monotonic() - t0 < 2.5


def test_another_identity_cannot_command_the_robot(secure, bridge):
    profile, _ = secure
    controller, _, received = bridge
    with session_as(profile, "validator") as intruder:
        lease = intruder.liveliness().declare_token("gd2p/lease/validator-1")
        time.sleep(0.3)
        before = servo_commands(controller)
        command = command_from_here(controller, "gd2p/lease/validator-1")
        assert send(intruder, command, timeout=1.5) == []  # the router drops the query: no reply at all
        intruder.put(COMMAND_KEY, b"from-validator")  # nor does a put get through
        time.sleep(0.3)
        lease.undeclare()
    assert command.id not in received and servo_commands(controller) == before
    assert "put:from-validator" not in received


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


def test_the_ordinary_bus_and_the_estop_stay_open_to_every_identity(secure, bridge):
    profile, _ = secure
    _, executor, _ = bridge
    with session_as(profile, "validator") as validator, session_as(profile, "cli") as operator:
        token = validator.liveliness().declare_token("gd2p/alive/validator/v-1")
        got = threading.Event()
        subscriber = operator.declare_subscriber("gd2p/status/validator/*", lambda sample: got.set())
        time.sleep(0.3)
        alive = [str(r.ok.key_expr) for r in operator.liveliness().get("gd2p/alive/**", timeout=2.0) if r.ok]
        assert "gd2p/alive/validator/v-1" in alive
        validator.put("gd2p/status/validator/v-1", b"ready")
        assert got.wait(2.0)
        subscriber.undeclare()
        token.undeclare()
        payload, encoding = encode(EStop(reason="secure e-stop test", issued_by="cli"))
        operator.put(ESTOP_KEY, payload, encoding=encoding)  # any identity may stop the robot
        deadline = time.monotonic() + 2.0
        while not executor.estop.triggered.is_set() and time.monotonic() < deadline:
            time.sleep(0.05)
    assert executor.estop.triggered.is_set() and executor.estop.last.reason == "secure e-stop test"
    executor.estop.reset()


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
        assert "gd2p/alive/robot_bridge/robot_bridge-1" in alive
    finally:
        launcher.stop()

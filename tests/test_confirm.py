"""Preview and confirm (`gd2p up --confirm`): the robot bridge holds each plan until an operator confirms it.

- the gate alone (shared/execution/confirm.py, no bus): confirmations for unknown, expired, dropped and
  already confirmed commands are answered accepted=False with the reason;
- the bus bridge with its simulated robot on a real router (tests/test_robot_bridge.py's BusBridge): a held
  plan does not move the robot until `client.confirm.confirm` releases it, then runs; one nobody confirms
  is refused "not_confirmed" and never moves; a lost lease or an e-stop while it waits drops it, and it
  never moves; the held key tells a view what waits and how each hold ended;
- the system (planner, validator, bridge with --confirm in threads, as tests/test_push.py): a push nobody
  confirms answers ErrorReply "not_confirmed" without a retry and without motion; a confirmed one runs.
The secure profile's rule (only the operator identity may confirm) is tested in tests/test_secure_bus.py.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from client.confirm import ConfirmError, confirm, held_plans
from conftest import TRUTH_TRACKED as TRUTH
from shared.bus.keys import ROBOT_HELD_KEY, ROBOT_STATE_KEY
from shared.contracts.codec import decode
from shared.contracts.messages import ExecutionCommand, ExecutionState, PlanConfirm, PlanHeld
from shared.execution.confirm import ConfirmGate
from shared.execution.executor import EStopLatch, LocalLease
from shared.execution.limits import SafetyRefusal
from test_robot_bridge import MOVE_RAD, BusBridge, home_configuration, straight_plan


# ------------------------------------------------------------------------------------------ the gate alone
def _command() -> ExecutionCommand:
    return ExecutionCommand(plan=straight_plan(home_configuration(), home_configuration(), 1.0), lease_token="test")


def _hold_in_thread(gate: ConfirmGate, command: ExecutionCommand, lease: LocalLease) -> tuple[threading.Thread, list]:
    outcome: list = []

    def hold() -> None:
        try:
            outcome.append(gate.hold(command, lease))
        except SafetyRefusal as exc:
            outcome.append(exc)

    thread = threading.Thread(target=hold, daemon=True)
    thread.start()
    deadline = time.monotonic() + 2.0
    while not any(h.command_id == command.id for h in gate.held()) and time.monotonic() < deadline:
        time.sleep(0.01)
    return thread, outcome


def test_a_confirmation_for_an_unknown_expired_dropped_or_confirmed_command_is_refused_with_why():
    announced: list[PlanHeld] = []
    gate = ConfirmGate(EStopLatch(), timeout_s=0.5, announce=announced.append)
    unknown = gate.confirm(PlanConfirm(command_id="no-such-id", operator="alice"))
    assert not unknown.accepted and "unknown command no-such-id" in unknown.reason

    confirmed = _command()
    thread, outcome = _hold_in_thread(gate, confirmed, LocalLease())
    first = gate.confirm(PlanConfirm(command_id=confirmed.id, operator="alice"))
    thread.join(2.0)
    assert first.accepted and first.reason == "confirmed by alice" and outcome == ["alice"]
    again = gate.confirm(PlanConfirm(command_id=confirmed.id, operator="bob"))
    assert not again.accepted and "already confirmed (by alice)" in again.reason

    expired = _command()
    thread, outcome = _hold_in_thread(gate, expired, LocalLease())
    thread.join(2.0)
    assert isinstance(outcome[0], SafetyRefusal) and outcome[0].check == "not_confirmed"
    late = gate.confirm(PlanConfirm(command_id=expired.id, operator="alice"))
    assert not late.accepted and "expired" in late.reason

    dropped, lease = _command(), LocalLease()
    thread, outcome = _hold_in_thread(gate, dropped, lease)
    lease.release("the planner gave up")
    thread.join(2.0)
    assert isinstance(outcome[0], SafetyRefusal) and outcome[0].check == "lease"
    gone = gate.confirm(PlanConfirm(command_id=dropped.id))
    assert not gone.accepted and "no longer held" in gone.reason and "the planner gave up" in gone.reason
    # Every hold was announced, and announced again when it ended, with how.
    ends = {h.command_id: h.reason for h in announced if h.reason is not None}
    assert ends[confirmed.id] == "confirmed by alice" and ends[expired.id].startswith("expired")
    assert ends[dropped.id].startswith("dropped: lease:") and gate.held() == []


def test_the_timeout_must_fit_in_the_planners_wait():
    with pytest.raises(ValueError, match="confirmation timeout"):
        ConfirmGate(EStopLatch(), timeout_s=600.0)


# ------------------------------------------------------------------------------------------ the bus bridge
class HeldListener:
    """Every PlanHeld published on the held key."""

    def __init__(self, session):
        self.seen: list[PlanHeld] = []
        self._subscriber = session.declare_subscriber(
            ROBOT_HELD_KEY, lambda s: self.seen.append(decode(s.payload.to_bytes(), str(s.encoding), PlanHeld)))

    def wait_held(self, timeout: float = 10.0) -> PlanHeld:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.seen:
                return self.seen[0]
            time.sleep(0.02)
        raise AssertionError("nothing was held")

    def ended(self, command_id: str) -> str | None:
        return next((h.reason for h in self.seen if h.command_id == command_id and h.reason is not None), None)

    def close(self) -> None:
        self._subscriber.undeclare()


@pytest.fixture()
def confirming_bridge(zenoh_router):
    bridge = BusBridge(zenoh_router, confirm_timeout_s=3.0)
    listener = HeldListener(bridge.commander)
    yield bridge, listener
    listener.close()
    bridge.close()


def _execute_in_thread(bridge: BusBridge, command: ExecutionCommand) -> tuple[threading.Thread, list[ExecutionState]]:
    result: list[ExecutionState] = []
    thread = threading.Thread(target=lambda: result.append(bridge.bridge.execute(command)), daemon=True)
    thread.start()
    return thread, result


def _moved(bridge: BusBridge) -> float:
    return float(abs(bridge.backend.observe().positions[0] - home_configuration()[0]))


def test_a_held_plan_does_not_move_the_robot_until_an_operator_confirms_it_then_runs(confirming_bridge):
    bridge, listener = confirming_bridge
    key, _token = bridge.lease("planner-1.held-1")
    command = bridge.move(key, duration_s=0.5)
    thread, result = _execute_in_thread(bridge, command)
    held = listener.wait_held()
    assert held.command_id == command.id and held.reason is None and held.expires_at > time.time()
    assert np.allclose(held.plan.positions.to_numpy(), command.plan.positions.to_numpy())
    listed = held_plans(bridge.commander)  # what `gd2p confirm --list` shows (the bridge repeats it every second)
    assert [h.command_id for h in listed] == [command.id]
    time.sleep(0.5)
    assert not result and _moved(bridge) < 1e-3  # still waiting, and nothing moved
    busy = bridge.bridge.execute(bridge.move(key, duration_s=0.5))  # the robot is taken while a plan waits
    assert busy.status == "refused" and "busy" in busy.message

    reply = confirm(bridge.commander, command.id, operator="alice")
    thread.join(10.0)
    assert reply.accepted and reply.command_id == command.id and "alice" in reply.reason
    assert result[0].status == "done", result[0].message
    assert "confirmed by alice" in result[0].message
    assert abs(bridge.travel(result[0]) - MOVE_RAD) < 0.01
    time.sleep(0.2)
    assert listener.ended(command.id) == "confirmed by alice"
    again = confirm(bridge.commander, command.id, operator="bob")
    assert not again.accepted and "already confirmed" in again.reason
    unknown = confirm(bridge.commander, "not-a-command")
    assert not unknown.accepted and "unknown command" in unknown.reason


def test_a_plan_nobody_confirms_is_dropped_and_never_moves(confirming_bridge):
    bridge, listener = confirming_bridge
    key, _token = bridge.lease("planner-1.held-2")
    command = bridge.move(key, duration_s=0.5)
    started = time.monotonic()
    state = bridge.bridge.execute(command)
    waited = time.monotonic() - started
    assert state.status == "refused" and state.message.startswith("not_confirmed:"), state.message
    assert 2.9 < waited < 5.0 and _moved(bridge) < 1e-3 and abs(bridge.travel(state)) < 1e-3
    time.sleep(0.2)
    assert (listener.ended(command.id) or "").startswith("expired")
    late = confirm(bridge.commander, command.id, operator="alice")
    assert not late.accepted and "expired" in late.reason
    assert _moved(bridge) < 1e-3


@pytest.mark.parametrize("fault", ["lease lost", "e-stop"])
def test_a_lease_lost_or_an_estop_while_a_plan_waits_drops_it_and_it_never_moves(confirming_bridge, fault):
    from services.robot_bridge.bus_safety import ESTOP_KEY

    bridge, listener = confirming_bridge
    key, token = bridge.lease(f"planner-1.held-{fault.replace(' ', '-')}")
    command = bridge.move(key, duration_s=0.5)
    thread, result = _execute_in_thread(bridge, command)
    listener.wait_held()
    t0 = time.monotonic()
    if fault == "lease lost":
        token.undeclare()
    else:
        bridge.commander.put(ESTOP_KEY, b"")
    thread.join(3.0)
    assert result and time.monotonic() - t0 < 1.0  # dropped at once, not at the timeout
    check = "lease" if fault == "lease lost" else "estop"
    assert result[0].status == "refused" and result[0].message.startswith(f"{check}:"), result[0].message
    assert "while the plan waited for confirmation" in result[0].message
    late = confirm(bridge.commander, command.id, operator="alice")  # too late: the plan is gone
    assert not late.accepted and "no longer held" in late.reason
    time.sleep(0.2)
    assert (listener.ended(command.id) or "").startswith(f"dropped: {check}:")
    assert _moved(bridge) < 1e-3


def test_confirm_without_a_confirming_bridge_says_none_answered(zenoh_router):
    bridge = BusBridge(zenoh_router)  # confirm off: nothing serves the confirm key
    try:
        with pytest.raises(ConfirmError, match=r"no robot bridge answered .* --confirm"):
            confirm(bridge.commander, "some-id", timeout_s=0.5)
        assert held_plans(bridge.commander, wait_s=0.2) == []
    finally:
        bridge.close()


# ------------------------------------------------------------------------------------------ the system
@pytest.fixture(scope="module")
def confirm_system(module_router, tmp_path_factory):
    """Planner, one validator and the simulated robot bridge with --confirm (a 4 s timeout) on the router."""
    from services.planner import service as planner
    from services.robot_bridge import service as bridge
    from shared.bus import BusConfig, live_workers, open_session, run_worker
    from shared.validation import jobs as validator

    cfg = BusConfig(mode="client", connect=[module_router], connect_timeout_ms=5000)
    record_dir = tmp_path_factory.mktemp("pushes")
    stop = threading.Event()
    workers = [
        threading.Thread(target=bridge.run, args=(cfg, "bridge-c", stop), kwargs={"confirm_timeout_s": 4.0, **TRUTH},
                         daemon=True),
        threading.Thread(target=run_worker, args=(validator.SERVICE, validator.handlers(), cfg, "validator-c"),
                         kwargs={"stop": stop}, daemon=True),
        threading.Thread(target=planner.run, args=(cfg, "planner-c", stop, str(record_dir)), daemon=True),
    ]
    for w in workers:
        w.start()
    session = open_session(cfg)
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        live = live_workers(session)
        if all(live.get(s) for s in ("planner", "validator", "robot_bridge")):
            break
        time.sleep(0.2)
    else:
        pytest.fail(f"workers did not register: {live}")
    yield cfg, session
    session.close()
    stop.set()
    for w in workers:
        w.join(timeout=15.0)


class StateListener:
    def __init__(self, session):
        self.statuses: list[str] = []
        self._subscriber = session.declare_subscriber(
            ROBOT_STATE_KEY,
            lambda s: self.statuses.append(decode(s.payload.to_bytes(), str(s.encoding), ExecutionState).status))

    def close(self) -> None:
        self._subscriber.undeclare()


def test_a_push_nobody_confirms_answers_not_confirmed_once_and_the_robot_never_moves(confirm_system):
    from client.push_client import PushFailed, push
    from shared.contracts.messages import ObjectRef, PlannerOptions, PushRequest

    cfg, session = confirm_system
    held, states = HeldListener(session), StateListener(session)
    try:
        with pytest.raises(PushFailed) as failed:
            push(PushRequest(object=ObjectRef(library_id="proc-box-013"), direction_deg=90.0, options=PlannerOptions(method="fixed", choice="random")), cfg, timeout_s=240.0)
        time.sleep(0.3)
    finally:
        held.close()
        states.close()
    assert failed.value.code == "not_confirmed", failed.value
    assert "not confirmed" in failed.value.message and "nothing moved" in failed.value.message
    assert len({h.command_id for h in held.seen}) == 1  # held once, dropped, never sent again
    assert states.statuses == []  # the robot streamed nothing: it never moved


def test_a_push_an_operator_confirms_runs(confirm_system):
    from client.push_client import push
    from shared.contracts.messages import ObjectRef, PlannerOptions, PushRequest

    cfg, session = confirm_system
    replies = []

    def operator(sample) -> None:  # what the live view's button does: confirm what is held
        held = decode(sample.payload.to_bytes(), str(sample.encoding), PlanHeld)
        if held.reason is None and not replies:
            threading.Thread(target=lambda: replies.append(confirm(session, held.command_id, "op-test")),
                             daemon=True).start()

    subscriber = session.declare_subscriber(ROBOT_HELD_KEY, operator)
    try:
        response = push(PushRequest(object=ObjectRef(library_id="proc-box-013"), direction_deg=90.0, options=PlannerOptions(method="fixed", choice="random")), cfg, timeout_s=240.0)
    finally:
        subscriber.undeclare()
    assert replies and replies[0].accepted
    assert response.result.success, response.result


# ------------------------------------------------------------------------------------------ where users reach it
def test_gd2p_confirm_lists_the_held_plan_and_releases_it(confirming_bridge, zenoh_router, capsys):
    from cli.main import main

    bridge, listener = confirming_bridge
    key, _token = bridge.lease("planner-1.held-cli")
    command = bridge.move(key, duration_s=0.5)
    thread, result = _execute_in_thread(bridge, command)
    listener.wait_held()
    bus = ["--connect", zenoh_router]
    assert main(["confirm", "--list", *bus]) == 0
    listed = capsys.readouterr().out
    assert command.id in listed and "panda+allegro" in listed
    assert main(["confirm", "no-such-id", *bus]) == 1
    assert "not accepted: unknown command no-such-id" in capsys.readouterr().err
    assert main(["confirm", command.id, "--operator", "carol", *bus]) == 0
    assert "confirmed by carol" in capsys.readouterr().out
    thread.join(10.0)
    assert result[0].status == "done" and "confirmed by carol" in result[0].message
    assert main(["confirm", command.id, *bus]) == 1
    assert "already confirmed (by carol)" in capsys.readouterr().err
    assert main(["confirm", *bus]) == 2


def test_gd2p_up_passes_confirm_to_the_bridge_process_only_when_asked(tmp_path):
    from deploy.launcher import Launcher

    off = Launcher(validators=0, record_dir=tmp_path, log_dir=tmp_path)
    on = Launcher(validators=0, record_dir=tmp_path, log_dir=tmp_path, confirm_timeout_s=30.0)
    assert off._command("robot_bridge", "robot_bridge-1")[-1] == "--no-confirm"
    assert on._command("robot_bridge", "robot_bridge-1")[-3:] == ["--confirm", "--confirm-timeout", "30"]
    assert "--confirm" not in on._command("planner", "planner-1")


@pytest.mark.parametrize(("flags", "expected", "warned"), [
    ([], None, False),  # the simulated robot: off
    (["--confirm", "--confirm-timeout", "12"], 12.0, False),
    (["--hardware", "xarm7+leap", "--xarm7-ip", "10.0.0.2", "--leap-port", "/dev/null"], 60.0, False),  # hardware: on
    (["--hardware", "xarm7+leap", "--xarm7-ip", "10.0.0.2", "--leap-port", "/dev/null", "--no-confirm"], None, True),
])
def test_the_bridge_confirms_by_default_on_hardware_only(monkeypatch, caplog, flags, expected, warned):
    from services.robot_bridge import __main__ as bridge_main

    calls: list[dict] = []
    monkeypatch.setattr(bridge_main, "run", lambda *args, **kwargs: calls.append(kwargs))
    monkeypatch.setattr(bridge_main, "configure_service_logging", lambda: None)
    with caplog.at_level("WARNING"):
        assert bridge_main.main(flags) == 0
    assert calls[0]["confirm_timeout_s"] == expected
    assert ("--no-confirm on hardware" in caplog.text) == warned


def test_a_confirm_timeout_beyond_the_planners_wait_is_refused(capsys):
    from services.robot_bridge import __main__ as bridge_main

    with pytest.raises(SystemExit):
        bridge_main.main(["--confirm", "--confirm-timeout", "900"])
    assert "--confirm-timeout must be in (0, 240] s" in capsys.readouterr().err


@pytest.mark.parametrize("payload", [b"", b"\xff\x00garbage", "PushRequest"])
def test_a_malformed_confirmation_gets_a_bad_request_and_releases_nothing(confirming_bridge, payload):
    from shared.bus.keys import ROBOT_CONFIRM_KEY
    from shared.contracts.codec import encode
    from shared.contracts.messages import ErrorReply, ObjectRef, PushRequest

    bridge, listener = confirming_bridge
    key, _token = bridge.lease("planner-1.held-bad")
    command = bridge.move(key, duration_s=0.5)
    thread, result = _execute_in_thread(bridge, command)
    listener.wait_held()
    if payload == "PushRequest":
        data, encoding = encode(PushRequest(object=ObjectRef(library_id="proc-box-013"), direction_deg=0.0))
    else:
        data, encoding = payload, "application/msgpack;PlanConfirm"
    replies = [r.ok for r in bridge.commander.get(ROBOT_CONFIRM_KEY, payload=data, encoding=encoding, timeout=5.0)
               if r.ok is not None]
    reply = decode(replies[0].payload.to_bytes(), str(replies[0].encoding))
    assert isinstance(reply, ErrorReply) and reply.code == "bad_request", reply
    time.sleep(0.3)
    assert not result and _moved(bridge) < 1e-3  # still held: garbage releases nothing
    assert confirm(bridge.commander, command.id, operator="alice").accepted
    thread.join(10.0)
    assert result[0].status == "done"

"""The local launcher end to end: real service processes on an embedded router on a free port.

One launcher is shared by the module (process start-up dominates the cost); the test that stops it
runs last. Every check goes through the bus, as a user's `gd2p status` / `scale_validators.py` would.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import cli.system
from deploy import scale_validators
from deploy.launcher import (
    MAX_SCALE_ENV,
    SERVICES,
    Launcher,
    LaunchError,
    default_scale_limits,
    free_loopback_endpoint,
    request_scale,
    scale_limits,
)
from shared.bus import BusConfig, Dispatcher, RemoteError, live_workers, open_session
from shared.contracts.messages import GenerationJob, ObjectRef

pytestmark = pytest.mark.timeout(120)
PROJECT_ROOT = Path(__file__).resolve().parents[1]


def eventually(condition, timeout: float = 60.0, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"{what} not reached within {timeout} s")


def gd2p_system(*argv: str) -> int:
    """Run a `cli.system` sub-command (status, health, ...) in-process; returns its exit code."""
    parser = argparse.ArgumentParser(prog="gd2p")
    cli.system.register(parser.add_subparsers())
    args = parser.parse_args(argv)
    return args.func(args)


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.fixture(scope="module")
def launcher(tmp_path_factory):
    root = tmp_path_factory.mktemp("launcher")
    system = Launcher(validators=1, listen=free_loopback_endpoint(), record_dir=root / "rec", log_dir=root / "logs",
                      max_scale={"validator": 2})
    system.start()
    try:
        system.wait_ready(60)
        yield system
    finally:
        system.stop()


@pytest.fixture(scope="module")
def client(launcher):
    with open_session(BusConfig(mode="client", connect=[launcher.endpoint], connect_timeout_ms=5000)) as session:
        yield session


def test_every_service_registers_and_status_counts_them(launcher, capsys):
    assert gd2p_system("status", "--json", "--connect", launcher.endpoint) == 0
    counts = json.loads(capsys.readouterr().out)
    assert counts == {svc: 1 for svc in SERVICES}


def test_status_without_router_fails_clearly(capsys):
    started = time.monotonic()
    assert gd2p_system("status", "--connect", free_loopback_endpoint()) != 0
    assert "no Zenoh router reachable" in capsys.readouterr().err
    assert time.monotonic() - started < 15


def test_health_command_asks_the_worker_itself(launcher, capsys):
    worker = launcher.expected_workers()["planner"][0]
    assert gd2p_system("health", "--service", "planner", "--worker-id", worker, "--connect", launcher.endpoint) == 0
    assert worker in capsys.readouterr().out
    assert gd2p_system("health", "--service", "planner", "--worker-id", "nobody", "--timeout", "1",
                       "--connect", launcher.endpoint) == 1


def test_a_bad_request_through_the_system_gets_a_clear_error_reply(client):
    """A job naming an object the library doesn't have is refused with a reply that names it."""
    job = GenerationJob(object=ObjectRef(library_id="no-such-object"), hand="allegro", batch_size=4)
    with Dispatcher(client, "generator", timeout_s=30.0) as dispatcher:
        with pytest.raises(RemoteError) as caught:
            dispatcher.call(job, timeout=60.0)
    assert caught.value.code == "bad_request"
    assert "no-such-object" in caught.value.message


def test_scale_validators_up_and_down_through_the_control_key(launcher, client, capsys):
    reply = request_scale(client, "validator", 2)
    assert (reply.count, len(reply.started), reply.stopped) == (2, 1, [])
    assert len(live_workers(client, "validator")["validator"]) == 2

    assert scale_validators.main(["1", "--connect", launcher.endpoint]) == 0
    assert "validators: 1" in capsys.readouterr().out
    eventually(lambda: len(live_workers(client, "validator").get("validator", [])) == 1, what="1 validator")
    assert len(launcher.expected_workers()["validator"]) == 1


def test_a_scale_request_above_the_maximum_is_refused_clearly(launcher, client):
    before = launcher.expected_workers()["validator"]
    for count in (3, 1024):  # the configured maximum is 2; ScaleRequest's own bound is 1024
        with pytest.raises(RemoteError) as caught:
            request_scale(client, "validator", count)
        assert caught.value.code == "bad_request"
        assert f"cannot scale validator to {count}: the maximum on this launcher is 2" in caught.value.message
        assert MAX_SCALE_ENV in caught.value.message
    assert launcher.expected_workers()["validator"] == before


def test_singletons_cannot_be_scaled(client):
    with pytest.raises(RemoteError) as caught:
        request_scale(client, "robot_bridge", 2)
    assert caught.value.code == "bad_request"


def test_crashed_service_is_restarted_and_reregisters(launcher, client):
    child = next(c for c in launcher.children() if c.service == "sampler")
    old_pid = child.pid
    os.kill(old_pid, signal.SIGKILL)
    eventually(lambda: child.restarts == 1 and child.pid != old_pid, what="sampler restart")
    eventually(lambda: child.worker_id in live_workers(client, "sampler").get("sampler", []), what="re-registration")
    assert any(e.worker_id == child.worker_id and e.returncode == -signal.SIGKILL for e in launcher.exits)


def test_stop_ends_every_process_within_10_s(launcher):
    pids = [c.pid for c in launcher.children()]
    assert pids and all(alive(pid) for pid in pids)
    started = time.monotonic()
    launcher.stop()
    assert time.monotonic() - started < 10.0
    assert not any(alive(pid) for pid in pids)


def test_a_service_dying_on_start_is_reported_with_its_output(tmp_path):
    class BrokenPlanner(Launcher):
        def _command(self, service: str, worker_id: str) -> list[str]:
            if service == "planner":
                return [sys.executable, "-c", "import sys; sys.exit('planner: cannot load the checkpoint')"]
            return super()._command(service, worker_id)

    system = BrokenPlanner(validators=0, listen=free_loopback_endpoint(), record_dir=tmp_path / "rec",
                           log_dir=tmp_path / "logs", restart=False)
    system.start()
    try:
        with pytest.raises(LaunchError, match=r"(?s)planner \(planner-1\) exited with code 1.*cannot load the checkpoint"):
            system.wait_ready(60)
    finally:
        system.stop()


def test_gd2p_up_stops_everything_on_sigterm(tmp_path):
    endpoint = free_loopback_endpoint()
    up = subprocess.Popen(
        [sys.executable, "-m", "cli.main", "up", "--validators", "1", "--listen", endpoint,
         "--record-dir", str(tmp_path / "rec"), "--log-dir", str(tmp_path / "logs")],
        cwd=PROJECT_ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        output = []
        for line in up.stdout:  # the launcher prints the table, then this line, once all registered
            output.append(line)
            if line.startswith("Ctrl-C"):
                break
        assert any(line.startswith("Ctrl-C") for line in output), "".join(output)
        table = "".join(output)
        pids = [int(row.split()[2]) for row in table.splitlines() if row.split()[:1] and row.split()[0] in SERVICES]
        assert len(pids) == len(SERVICES)
        started = time.monotonic()
        up.send_signal(signal.SIGTERM)
        assert up.wait(timeout=15) == 0
        assert time.monotonic() - started < 10.0
        assert not any(alive(pid) for pid in pids)
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()


def test_scale_limits_follow_the_cores_and_are_configurable(monkeypatch, tmp_path):
    assert default_scale_limits(2) == {"generator": 2, "planner": 2, "sampler": 2, "validator": 8}
    assert default_scale_limits(1)["validator"] == 4 and default_scale_limits(8)["planner"] == 8
    from_env = scale_limits(environ={MAX_SCALE_ENV: "validator=16, planner=3"}, cpus=2)
    assert from_env == {"generator": 2, "planner": 3, "sampler": 2, "validator": 16}
    assert scale_limits({"validator": 1}, environ={MAX_SCALE_ENV: "validator=16"}, cpus=2)["validator"] == 1
    for bad in ("robot_bridge=2", "validator", "validator=many", "validator=-1", "validator=1025"):
        with pytest.raises(LaunchError, match=MAX_SCALE_ENV):
            scale_limits(environ={MAX_SCALE_ENV: bad}, cpus=2)
    with pytest.raises(LaunchError, match="the maximum on this launcher is 2"):
        Launcher(validators=3, max_scale={"validator": 2}, log_dir=tmp_path / "logs")
    monkeypatch.setenv(MAX_SCALE_ENV, "validator=1")
    system = Launcher(log_dir=tmp_path / "logs")  # default: one validator per core, within the maximum
    assert system.max_scale["validator"] == 1 and system.initial_counts["validator"] == 1
    assert system.scale_refusal("validator", 1) is None and "maximum" in system.scale_refusal("validator", 2)


def test_the_simulated_robot_s_engine_and_tracking_reach_the_bridge_and_bad_ones_are_refused(tmp_path, capsys):
    system = Launcher(validators=0, log_dir=tmp_path / "logs", robot="mujoco", tracking="truth")
    command = system._command("robot_bridge", "robot_bridge-1")
    assert command[command.index("--robot") + 1] == "mujoco" and command[command.index("--tracking") + 1] == "truth"
    with pytest.raises(LaunchError, match="unknown tracking 'oracle'; known: image, truth"):
        Launcher(validators=0, log_dir=tmp_path / "logs", tracking="oracle")
    from services.robot_bridge.__main__ import main as bridge_main

    with pytest.raises(SystemExit) as exit_info:
        bridge_main(["--hardware", "panda+allegro", "--panda-host", "10.0.0.2", "--tracking", "truth"])
    assert exit_info.value.code == 2 and "with --hardware your tracker does" in capsys.readouterr().err

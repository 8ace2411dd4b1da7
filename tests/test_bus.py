"""Bus layer: session config, key expressions, the worker runtime and discovery, against a real router."""
from __future__ import annotations

import argparse
import json
import signal
import subprocess
import threading
import time

import msgpack
import pytest
import zenoh

import bus_test_workers as tw
from conftest import free_port, router_config
from shared.bus import (
    BusConfig,
    BusError,
    Dispatcher,
    RouterUnreachable,
    Worker,
    alive_key,
    health,
    job_key,
    live_workers,
    open_session,
    parse_alive_key,
    status_key,
)
from shared.contracts.codec import decode, encode
from shared.contracts.errors import ServiceError
from shared.contracts.messages import ErrorReply, HealthQuery, WorkerStatus

pytestmark = pytest.mark.timeout(60)


# ---------------------------------------------------------------------------------------- helpers
def wait_until(predicate, timeout: float = 10.0, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def request(session: zenoh.Session, key: str, payload: bytes, encoding: str | None) -> ErrorReply | object:
    """One raw query; returns the single decoded reply (asserts exactly one arrives)."""
    replies = [r for r in session.get(key, payload=payload, encoding=encoding, timeout=10.0)]
    assert len(replies) == 1, f"expected one reply, got {len(replies)}"
    assert replies[0].ok is not None, replies[0].err.payload.to_string()
    return decode(replies[0].ok.payload.to_bytes(), str(replies[0].ok.encoding))


def start_worker(endpoint: str, worker_id: str, concurrency: int = 1) -> subprocess.Popen:
    return subprocess.Popen(tw.worker_command(endpoint, worker_id, concurrency))


def stop_process(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait(10)


@pytest.fixture(scope="module")
def router(module_router):
    return module_router


@pytest.fixture(scope="module")
def client(router):
    session = open_session(BusConfig(connect=[router], connect_timeout_ms=5000))
    yield session
    session.close()


@pytest.fixture(scope="module")
def echo_worker(router, client):
    """One worker process for the request/response checks; yields its job key."""
    proc = start_worker(router, "echo-1")
    wait_until(lambda: "echo-1" in live_workers(client, tw.SERVICE).get(tw.SERVICE, []), 30, "the echo worker")
    yield job_key(tw.SERVICE, "echo-1")
    stop_process(proc)


# ---------------------------------------------------------------------------------------- config
def test_config_defaults_per_mode():
    assert BusConfig().connect == ["tcp/127.0.0.1:7447"]
    assert BusConfig(mode="router").listen == ["tcp/127.0.0.1:7447"]
    assert BusConfig(mode="peer").connect == []
    with pytest.raises(BusError, match="unknown Zenoh mode 'server'"):
        BusConfig(mode="server")
    with pytest.raises(BusError, match="does not exist"):
        BusConfig(config_file="/nonexistent/zenoh.json5")


def test_config_from_env_and_flags(monkeypatch, tmp_path):
    monkeypatch.setenv("GD2P_ZENOH_CONNECT", "tcp/10.0.0.1:7447, tcp/10.0.0.2:7447")
    monkeypatch.setenv("GD2P_ZENOH_MODE", "peer")
    cfg = BusConfig.from_env()
    assert (cfg.mode, cfg.connect) == ("peer", ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"])

    parser = argparse.ArgumentParser()
    BusConfig.add_cli_args(parser)
    from_env = BusConfig.from_args(parser.parse_args([]))
    assert (from_env.mode, from_env.connect) == ("peer", ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"])
    flags = BusConfig.from_args(parser.parse_args(["--mode", "client", "--connect", "tcp/h:1"]), connect_timeout_ms=500)
    assert (flags.mode, flags.connect, flags.connect_timeout_ms) == ("client", ["tcp/h:1"], 500)

    # A config file is merged first; explicit settings win, multicast scouting is always off.
    conf = tmp_path / "zenoh.json5"
    conf.write_text('{ mode: "peer", connect: { endpoints: ["tcp/file:1"] }, scouting: { multicast: { enabled: true } } }')
    zcfg = BusConfig(mode="client", config_file=str(conf)).to_zenoh()
    setting = lambda key: json.loads(zcfg.get_json(key))  # noqa: E731
    assert setting("mode") == "client"
    assert setting("connect/endpoints") == ["tcp/file:1"]
    assert setting("scouting/multicast/enabled") is False
    assert setting("connect/timeout_ms") == -1


def test_client_without_router_fails_clearly_with_finite_timeout():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(RouterUnreachable, match=f"no Zenoh router reachable at {endpoint}"):
        open_session(BusConfig(connect=[endpoint], connect_timeout_ms=300))


def test_invalid_endpoint_is_a_clear_error():
    with pytest.raises(BusError, match="Endpoints must be of the form"):
        BusConfig(connect=["bogus"]).to_zenoh()


def test_worker_waiting_for_a_router_stops_on_sigterm():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen(tw.worker_command(endpoint, "never-connected"), stderr=subprocess.PIPE, text=True)
    try:
        for line in proc.stderr:  # wait until it is inside the connect wait
            if f"no Zenoh router reachable at {endpoint}" in line:
                break
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(5) == 0
    finally:
        stop_process(proc)


def test_key_expressions():
    assert alive_key("validator", "w1") == "gd2p/alive/validator/w1"
    assert job_key("validator", "w1") == "gd2p/validator/worker/w1/job"
    assert status_key("validator", "w1") == "gd2p/status/validator/w1"
    assert parse_alive_key("gd2p/alive/validator/w1") == ("validator", "w1")
    for bad in ("", "a/b", "a*", "x$y"):
        with pytest.raises(BusError, match="invalid worker id"):
            alive_key("validator", bad)


def test_service_error_rejects_unknown_code():
    with pytest.raises(ValueError, match="not one of"):
        ServiceError("oops", "x")


# ---------------------------------------------------------------------------------------- worker runtime
def test_worker_answers_a_job_with_its_id(client, echo_worker):
    job = tw.BusTestJob(text="hello")
    reply = request(client, echo_worker, *encode(job))
    assert isinstance(reply, tw.BusTestResult)
    assert (reply.text, reply.worker_id, reply.id) == ("hello", "echo-1", job.id)


def test_malformed_payloads_get_bad_request_and_worker_survives(client, echo_worker):
    cases = {
        "not msgpack": (b"\xc1\xc1\xc1", "application/msgpack;BusTestJob", "not valid msgpack"),
        "wrong field type": (msgpack.packb({"text": 5}), "application/msgpack;BusTestJob", "text"),
        "unknown model": (msgpack.packb({}), "application/msgpack;NoSuchModel", "unknown message type 'NoSuchModel'"),
        "no encoding": (b"\x80", None, "unsupported encoding 'zenoh/bytes'"),
        "foreign encoding": (b"{}", "application/json", "unsupported encoding"),
    }
    for name, (payload, encoding, expected) in cases.items():
        reply = request(client, echo_worker, payload, encoding)
        assert isinstance(reply, ErrorReply), name
        assert reply.code == "bad_request", name
        assert expected in reply.message, (name, reply.message)
    assert request(client, echo_worker, *encode(tw.BusTestJob(text="still here"))).text == "still here"


def test_message_type_without_handler_is_named(client, echo_worker):
    stray = WorkerStatus(service="x", worker_id="y", pid=1, host="h")
    reply = request(client, echo_worker, *encode(stray))
    assert isinstance(reply, ErrorReply) and reply.code == "bad_request"
    assert reply.message == "bustest accepts BusTestJob; got WorkerStatus"
    assert reply.id == stray.id


def test_handler_errors_become_error_replies(client, echo_worker):
    infeasible = request(client, echo_worker, *encode(tw.BusTestJob(text="t", fail="service")))
    assert (infeasible.code, infeasible.message) == ("infeasible", "asked to fail: t")
    crash = request(client, echo_worker, *encode(tw.BusTestJob(fail="crash")))
    assert crash.code == "internal" and "ZeroDivisionError" in crash.message
    assert request(client, echo_worker, *encode(tw.BusTestJob(text="after crash"))).text == "after crash"


def test_health_query_and_idempotent_job_ids(client, echo_worker):
    before = request(client, echo_worker, *encode(HealthQuery()))
    assert isinstance(before, WorkerStatus)
    assert (before.service, before.worker_id, before.pid > 0) == ("bustest", "echo-1", True)

    job = tw.BusTestJob(text="once")
    first = request(client, echo_worker, *encode(job))
    again = request(client, echo_worker, *encode(job))  # a re-sent job id: served from the cache
    assert first == again
    after = request(client, echo_worker, *encode(HealthQuery()))
    assert after.jobs_done == before.jobs_done + 1

    statuses = health(client, tw.SERVICE)
    assert [s.worker_id for s in statuses] == ["echo-1"]


def test_in_process_worker_stops_on_event(router, client):
    stop = threading.Event()
    worker = Worker(tw.SERVICE, {tw.BusTestJob: tw.make_handler("inproc")}, worker_id="inproc", stop=stop,
                    session=client, status_period_s=0.2)
    thread = threading.Thread(target=worker.run)
    thread.start()
    wait_until(lambda: "inproc" in live_workers(client, tw.SERVICE).get(tw.SERVICE, []), 10, "the in-process worker")
    assert request(client, job_key(tw.SERVICE, "inproc"), *encode(tw.BusTestJob(text="x"))).worker_id == "inproc"
    stop.set()
    thread.join(10)
    assert not thread.is_alive()
    wait_until(lambda: "inproc" not in live_workers(client, tw.SERVICE).get(tw.SERVICE, []), 10, "token removal")


def test_stopping_worker_abandons_jobs_that_outlast_the_drain_timeout(client):
    stop = threading.Event()
    worker = Worker(tw.SERVICE, {tw.BusTestJob: tw.make_handler("slowpoke")}, worker_id="slowpoke", stop=stop,
                    session=client, drain_timeout_s=0.2)
    thread = threading.Thread(target=worker.run)
    thread.start()
    wait_until(lambda: "slowpoke" in live_workers(client, tw.SERVICE).get(tw.SERVICE, []), 10, "the worker")
    replies = client.get(job_key(tw.SERVICE, "slowpoke"), payload=encode(tw.BusTestJob(sleep_s=5))[0],
                         encoding="application/msgpack;BusTestJob", timeout=10)
    wait_until(lambda: worker.status().in_flight == 1, 5, "the job to start")
    stop.set()
    thread.join(5)
    assert not thread.is_alive()
    [reply] = list(replies)
    answer = decode(reply.ok.payload.to_bytes(), str(reply.ok.encoding))
    assert isinstance(answer, ErrorReply) and answer.code == "unavailable"
    assert "stopped before finishing" in answer.message


# ---------------------------------------------------------------------------------------- lifecycle
def test_sigterm_closes_worker_cleanly(router, client):
    statuses: list[WorkerStatus] = []
    sub = client.declare_subscriber(
        status_key(tw.SERVICE, "term-1"),
        lambda s: statuses.append(decode(s.payload.to_bytes(), str(s.encoding), WorkerStatus)),
    )
    proc = start_worker(router, "term-1")
    try:
        wait_until(lambda: statuses, 30, "a status heartbeat")
        assert statuses[0].state == "ready"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
        wait_until(lambda: "term-1" not in live_workers(client, tw.SERVICE).get(tw.SERVICE, []), 10, "token removal")
        wait_until(lambda: statuses[-1].state == "stopping", 5, "the final 'stopping' status")
    finally:
        sub.undeclare()
        stop_process(proc)


def test_router_started_after_clients():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = start_worker(endpoint, "late-1")  # connect_timeout_ms=-1: keeps retrying
    opened: dict[str, zenoh.Session] = {}
    opener = threading.Thread(target=lambda: opened.setdefault("s", open_session(BusConfig(connect=[endpoint]))))
    opener.start()
    time.sleep(1.5)
    assert opener.is_alive(), "a client with connect_timeout_ms=-1 must wait for the router"
    router = zenoh.open(router_config(endpoint))
    try:
        opener.join(30)
        session = opened["s"]
        with Dispatcher(session, tw.SERVICE, timeout_s=10) as dispatcher:
            dispatcher.wait_for_workers(1, timeout=30)
            assert dispatcher.call(tw.BusTestJob(text="late"), timeout=10).worker_id == "late-1"
        session.close()
    finally:
        stop_process(proc)
        router.close()

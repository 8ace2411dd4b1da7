"""Dispatcher: load balancing, back-pressure, re-dispatch on worker loss / timeout, exactly-once results."""
from __future__ import annotations

import subprocess
import time
from collections import Counter

import pytest

import bus_test_workers as tw
from shared.bus import BusConfig, BusError, Dispatcher, DispatchError, RemoteError, alive_key, job_key, open_session
from shared.contracts.messages import DEFAULT_MAX_PAYLOAD_BYTES, ErrorReply

pytestmark = pytest.mark.timeout(60)


def start_workers(endpoint: str, ids: list[str], concurrency: int, service: str = tw.SERVICE) -> list[subprocess.Popen]:
    return [subprocess.Popen(tw.worker_command(endpoint, wid, concurrency, service)) for wid in ids]


def stop_all(procs: list[subprocess.Popen]) -> None:
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
    for proc in procs:
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


@pytest.fixture(scope="module")
def router(module_router):
    return module_router


@pytest.fixture(scope="module")
def session(router):
    s = open_session(BusConfig(connect=[router], connect_timeout_ms=5000))
    yield s
    s.close()


@pytest.fixture(scope="module")
def two_workers(router, session):
    """Two worker processes that could run 8 jobs at once each (the dispatcher must limit them)."""
    procs = start_workers(router, ["pool-a", "pool-b"], concurrency=8)
    with Dispatcher(session, tw.SERVICE) as probe:
        probe.wait_for_workers(2, timeout=30)
    yield ["pool-a", "pool-b"]
    stop_all(procs)


def test_in_flight_per_worker_never_exceeds_the_limit(session, two_workers):
    with Dispatcher(session, tw.SERVICE, max_in_flight_per_worker=2, timeout_s=10) as dispatcher:
        dispatcher.wait_for_workers(2, timeout=10)
        jobs = [tw.BusTestJob(text=str(i), sleep_s=0.02) for i in range(40)]
        results = list(dispatcher.map(jobs))
    assert sorted(r.id for r in results) == sorted(j.id for j in jobs)
    by_worker = Counter(r.worker_id for r in results)
    assert set(by_worker) == set(two_workers), by_worker
    # Each worker could run 8 at once; the dispatcher allowed 2 (and did use both slots).
    assert max(r.concurrent for r in results) == 2


def test_submit_is_idempotent_by_job_id(session, two_workers):
    with Dispatcher(session, tw.SERVICE, timeout_s=10) as dispatcher:
        dispatcher.wait_for_workers(2, timeout=10)
        job = tw.BusTestJob(text="same", sleep_s=0.05)
        first = dispatcher.submit(job)
        assert dispatcher.submit(job) is first  # in flight
        result = first.result(10)
        assert dispatcher.submit(tw.BusTestJob(id=job.id, text="same", sleep_s=0.05)) is first  # recently completed
        assert result.id == job.id
        assert dispatcher.stats()[result.worker_id]["answered"] >= 1
        assert sum(w["dispatched"] for w in dispatcher.stats().values()) == 1


def test_a_different_job_under_a_known_id_is_refused(session, two_workers):
    with Dispatcher(session, tw.SERVICE, timeout_s=10) as dispatcher:
        dispatcher.wait_for_workers(1, timeout=10)
        job = tw.BusTestJob(text="mine", sleep_s=0.3)
        first = dispatcher.submit(job)
        with pytest.raises(BusError, match=f"job id {job.id} was reused for a different job"):
            dispatcher.submit(tw.BusTestJob(id=job.id, text="theirs"))  # in flight
        assert first.result(10).text == "mine"
        with pytest.raises(BusError, match="reused for a different job"):
            dispatcher.submit(tw.BusTestJob(id=job.id, text="theirs"))  # recently completed
        assert sum(w["dispatched"] for w in dispatcher.stats().values()) == 1


def test_remote_errors_surface_as_remote_error(session, two_workers):
    with Dispatcher(session, tw.SERVICE, timeout_s=10) as dispatcher:
        dispatcher.wait_for_workers(1, timeout=10)
        with pytest.raises(RemoteError, match="bustest: infeasible: asked to fail: x") as info:
            dispatcher.call(tw.BusTestJob(text="x", fail="service"), timeout=10)
        assert info.value.code == "infeasible"


@pytest.fixture()
def hung_worker(session):
    """A worker of service "bustest-hung" that takes queries and never answers (a hung process)."""
    service, worker_id = "bustest-hung", "hung-1"
    held: list = []  # queries kept unanswered (a dropped query would end without a reply)
    queryable = session.declare_queryable(job_key(service, worker_id), held.append, complete=True)
    token = session.liveliness().declare_token(alive_key(service, worker_id))
    yield service, held
    token.undeclare()
    queryable.undeclare()


def test_an_unanswered_job_is_retried_then_fails_clearly(session, hung_worker):
    service, held = hung_worker
    with Dispatcher(session, service, timeout_s=0.3, max_attempts=2) as dispatcher:
        dispatcher.wait_for_workers(1, timeout=10)
        slow = tw.BusTestJob(text="slow")
        with pytest.raises(DispatchError, match=rf"BusTestJob {slow.id}: no result from a {service} worker after 2 attempt") as info:
            dispatcher.call(slow, timeout=10)
        assert info.value.code == "timeout"
        assert "did not answer" in str(info.value)
        assert len(held) == 2
        # map() reports the same failure as an ErrorReply instead of aborting the batch.
        [reply] = list(dispatcher.map([tw.BusTestJob(text="slow2")]))
        assert isinstance(reply, ErrorReply) and reply.code == "timeout"


def test_a_job_past_its_deadline_is_answered_once_not_redispatched(session, two_workers):
    with Dispatcher(session, tw.SERVICE, timeout_s=2.0, max_attempts=3) as dispatcher:
        dispatcher.wait_for_workers(2, timeout=10)
        started = time.monotonic()
        # The worker's deadline watcher or the handler's own check_deadline, whichever comes first (a loaded CI
        # machine lets the handler win): either way one "timeout" answer naming the deadline.
        with pytest.raises(RemoteError, match=r"(did not finish within|ran past) its deadline of 1\.8 s") as info:
            dispatcher.call(tw.BusTestJob(text="endless", spin_s=30), timeout=10)
        assert info.value.code == "timeout"
        assert time.monotonic() - started < 3.0  # the worker answered before the query timed out
        assert sum(w["dispatched"] for w in dispatcher.stats().values()) == 1  # final: no other worker tried it


def test_an_oversized_job_is_refused_once_not_redispatched(session, two_workers):
    with Dispatcher(session, tw.SERVICE, timeout_s=20, max_attempts=3) as dispatcher:
        dispatcher.wait_for_workers(2, timeout=10)
        oversized = tw.BusTestJob(text="x" * (DEFAULT_MAX_PAYLOAD_BYTES + 1))
        with pytest.raises(RemoteError, match="exceeds the limit") as info:
            dispatcher.call(oversized, timeout=30)
        assert info.value.code == "bad_request"
        assert sum(w["dispatched"] for w in dispatcher.stats().values()) == 1


def test_closing_fails_pending_jobs_and_waiting_is_bounded(session):
    dispatcher = Dispatcher(session, "nobody-serves-this")
    with pytest.raises(TimeoutError, match="only 0 of 1 nobody-serves-this worker"):
        dispatcher.wait_for_workers(1, timeout=0.2)
    future = dispatcher.submit(tw.BusTestJob(text="orphan"))
    dispatcher.close()
    with pytest.raises(DispatchError, match="closed"):
        future.result(5)
    with pytest.raises(DispatchError, match="closed"):
        dispatcher.submit(tw.BusTestJob())


def test_worker_killed_mid_run_every_result_exactly_once(router, session, caplog):
    service = "bustest-kill"  # its own service: the module's pool workers must not take these jobs
    procs = start_workers(router, ["kill-a", "kill-b", "kill-c"], concurrency=2, service=service)
    try:
        with Dispatcher(session, service, max_in_flight_per_worker=2, timeout_s=10) as dispatcher:
            dispatcher.wait_for_workers(3, timeout=30)
            jobs = [tw.BusTestJob(text=f"job-{i}", sleep_s=0.01) for i in range(200)]
            futures = [dispatcher.submit(job) for job in jobs]
            delivered: Counter = Counter()
            for future in futures:
                future.add_done_callback(lambda f: delivered.update([f.result().id]))
            # Kill a worker once a quarter of the jobs are done: some of its jobs are in flight.
            deadline = time.monotonic() + 30
            while sum(f.done() for f in futures) < 50 and time.monotonic() < deadline:
                time.sleep(0.005)
            victim = procs[0]
            victim.kill()
            results = [f.result(30) for f in futures]
    finally:
        stop_all(procs)
    assert [r.id for r in results] == [j.id for j in jobs]
    assert [r.text for r in results] == [j.text for j in jobs]
    assert len(delivered) == 200 and set(delivered.values()) == {1}
    by_worker = Counter(r.worker_id for r in results)
    assert by_worker["kill-a"] > 0 and by_worker["kill-b"] > 0 and by_worker["kill-c"] > 0, by_worker
    assert by_worker["kill-b"] + by_worker["kill-c"] > by_worker["kill-a"]
    # The victim's in-flight jobs really were re-dispatched (and still delivered once, above).
    redispatched = [r for r in caplog.records if "kill-a" in r.getMessage() and "failed" in r.getMessage()]
    assert redispatched, "the killed worker had no job in flight: nothing was re-dispatched"

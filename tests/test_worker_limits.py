"""Worker limits: job ids bound to their content, bounded request sizes, per-job deadlines."""
from __future__ import annotations

import threading
import time

import pytest

import bus_test_workers as tw
from shared.bus import BusConfig, Worker, job_key, live_workers, open_session
from shared.bus.worker import timeout_attachment
from shared.contracts.codec import decode, encode
from shared.contracts.messages import (
    DEFAULT_MAX_PAYLOAD_BYTES,
    ErrorReply,
    GenerationJob,
    GenerationResult,
    Message,
    ObjectRef,
)

pytestmark = pytest.mark.timeout(60)


def wait_until(predicate, timeout: float = 10.0, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


@pytest.fixture(scope="module")
def client(module_router):
    session = open_session(BusConfig(connect=[module_router], connect_timeout_ms=5000))
    yield session
    session.close()


@pytest.fixture()
def serve(client):
    """Start in-process workers on the shared session: serve(worker_id, **options) -> (Worker, job key).

    They serve BusTestJob as the `bustest` service unless `service` and `handlers` say otherwise."""
    started: list[tuple[Worker, threading.Thread]] = []

    def start(worker_id: str, service: str = tw.SERVICE, handlers=None, **options) -> tuple[Worker, str]:
        handlers = handlers or {tw.BusTestJob: tw.make_handler(worker_id)}
        worker = Worker(service, handlers, worker_id=worker_id, session=client, status_period_s=0.2, **options)
        thread = threading.Thread(target=worker.run)
        thread.start()
        started.append((worker, thread))
        wait_until(lambda: worker_id in live_workers(client, service).get(service, []), 10, worker_id)
        return worker, job_key(service, worker_id)

    yield start
    for worker, thread in started:
        worker.stop()
        thread.join(15)


def send(client, key: str, job: Message, timeout_s: float | None = None, payload: bytes | None = None):
    """Send a job as a raw query; returns a function waiting for its one decoded reply."""
    body, encoding = encode(job)
    attachment = timeout_attachment(timeout_s) if timeout_s is not None else None
    replies = client.get(key, payload=body if payload is None else payload, encoding=encoding, timeout=30,
                         attachment=attachment)

    def answer():
        [reply] = list(replies)
        return decode(reply.ok.payload.to_bytes(), str(reply.ok.encoding))

    return answer


# ---------------------------------------------------------------------------------------- job ids
def test_a_job_id_reused_for_a_different_job_is_refused(client, serve):
    _, key = serve("ids-1")
    running = tw.BusTestJob(text="first", sleep_s=0.5)
    first = send(client, key, running)
    time.sleep(0.1)
    impostor = send(client, key, tw.BusTestJob(id=running.id, text="second"))()  # while the first runs
    assert isinstance(impostor, ErrorReply) and impostor.code == "bad_request", impostor
    assert f"job id {running.id} was reused for a different job" in impostor.message
    assert first().text == "first"
    after = send(client, key, tw.BusTestJob(id=running.id, text="second"))()  # once the first is cached
    assert isinstance(after, ErrorReply) and "reused for a different job" in after.message
    assert send(client, key, running)().text == "first"  # the same job again: the cached reply


# ---------------------------------------------------------------------------------------- sizes
def test_an_oversized_job_is_refused_without_decoding(client, serve, monkeypatch):
    decoded: list[int] = []
    real_decode = decode
    monkeypatch.setattr("shared.bus.worker.decode", lambda payload, *a: decoded.append(len(payload)) or real_decode(payload, *a))
    _, key = serve("size-1")
    big = tw.BusTestJob(text="x" * (DEFAULT_MAX_PAYLOAD_BYTES + 1))
    reply = send(client, key, big)()
    assert isinstance(reply, ErrorReply) and reply.code == "bad_request", reply
    size = len(encode(big)[0])
    assert f"BusTestJob payload of {size} bytes exceeds the limit of {DEFAULT_MAX_PAYLOAD_BYTES} bytes" in reply.message
    assert decoded == []
    assert send(client, key, tw.BusTestJob(text="small"))().text == "small"


# ---------------------------------------------------------------------------------------- deadlines
def test_a_slow_job_does_not_starve_a_normal_job_past_its_deadline(client, serve):
    worker, key = serve("starve-1", concurrency=1)
    started = time.monotonic()
    slow = send(client, key, tw.BusTestJob(text="huge", spin_s=30), timeout_s=1.0)  # its caller waits 1 s
    time.sleep(0.05)
    normal = send(client, key, tw.BusTestJob(text="normal"), timeout_s=20)
    assert normal().text == "normal"
    assert time.monotonic() - started < 2.0  # waited for the slow job's deadline, not its 30 s
    answer = slow()
    assert isinstance(answer, ErrorReply) and answer.code == "timeout", answer
    # The watchdog ("did not finish within its deadline") or the job's own check ("ran past its deadline"),
    # whichever answers first under load: both are the caller's deadline less the reply margin.
    assert "deadline of 0.9 s" in answer.message, answer.message
    wait_until(lambda: worker.status().in_flight == 0, 2, "the slow job's thread to stop")


def test_the_worker_deadline_bounds_jobs_and_timeouts_are_not_cached(client, serve):
    worker, key = serve("deadline-1", job_deadline_s=0.3)
    spinning = tw.BusTestJob(spin_s=30)
    started = time.monotonic()
    answer = send(client, key, spinning)()  # no caller timeout: the worker's own deadline applies
    assert isinstance(answer, ErrorReply) and answer.code == "timeout" and answer.id == spinning.id
    assert time.monotonic() - started < 1.5
    wait_until(lambda: worker.status().in_flight == 0, 2, "the job to stop at its next check")

    late = tw.BusTestJob(text="late", sleep_s=0.6)  # ignores the deadline, finishes after it
    assert send(client, key, late)().code == "timeout"
    wait_until(lambda: worker.status().in_flight == 0, 3, "the late job to finish")
    again = send(client, key, late)()  # neither the timeout nor the late result was cached: it runs again
    assert isinstance(again, ErrorReply) and again.code == "timeout"
    assert worker.status().jobs_done == 0


def test_a_generation_job_past_its_deadline_stops_between_iterations(client, serve):
    from services.generator.service import run_job

    worker, key = serve("gen-1", service="generator-deadline", handlers={GenerationJob: run_job})
    box = ObjectRef(library_id="proc-box-001")
    warm = send(client, key, GenerationJob(object=box, hand="allegro", batch_size=2, iterations=5))()
    assert isinstance(warm, GenerationResult)  # scene and hand loaded: the next job only optimises
    endless = GenerationJob(object=box, hand="allegro", batch_size=2, iterations=100_000)  # minutes of work
    started = time.monotonic()
    answer = send(client, key, endless, timeout_s=1.5)()
    assert isinstance(answer, ErrorReply) and answer.code == "timeout", answer
    wait_until(lambda: worker.status().in_flight == 0, 3.0 - (time.monotonic() - started), "the optimisation to stop")


# ---------------------------------------------------------------------------------------- queue bound
def test_a_full_queue_answers_busy_at_once_and_queues_nothing(client, serve):
    worker, key = serve("queue-1", concurrency=1, max_queued=1)
    running = send(client, key, tw.BusTestJob(text="running", sleep_s=1.0))
    wait_until(lambda: worker.status().in_flight == 1, 2, "the first job to start")
    queued = send(client, key, tw.BusTestJob(text="queued"))
    wait_until(lambda: worker.status().in_flight == 2, 2, "the second job to queue")
    started = time.monotonic()
    refused = send(client, key, tw.BusTestJob(text="one too many"))()
    assert time.monotonic() - started < 0.5, "a full queue must answer at once"
    assert isinstance(refused, ErrorReply) and refused.code == "busy", refused
    assert "2 jobs running or queued (its limit)" in refused.message
    assert running().text == "running" and queued().text == "queued"
    assert send(client, key, tw.BusTestJob(text="later"))().text == "later"  # room again: served


def test_a_flood_of_jobs_leaves_the_worker_answering_and_its_queue_bounded(client, serve):
    worker, key = serve("flood-1", concurrency=1, max_queued=2)
    answers = [send(client, key, tw.BusTestJob(text=f"job-{i}", sleep_s=0.05)) for i in range(200)]
    peak = 0
    replies = []
    for answer in answers:
        peak = max(peak, worker.status().in_flight)
        replies.append(answer())
    busy = [r for r in replies if isinstance(r, ErrorReply)]
    assert all(r.code == "busy" for r in busy) and len(busy) >= 150, [r.code for r in busy][:5]
    assert peak <= 3
    assert send(client, key, tw.BusTestJob(text="after the flood"))().text == "after the flood"


# ---------------------------------------------------------------------------------------- callers
def test_the_jobs_of_a_caller_that_went_away_are_cancelled(module_router, serve):
    """A Dispatcher whose session closes (Ctrl-C, a crash) takes its jobs with it: the running one stops at its next
    check, the queued one never starts, and the worker is free for the next caller at once."""
    from shared.bus import Dispatcher

    worker, key = serve("callers-1", concurrency=1)
    cfg = BusConfig(connect=[module_router], connect_timeout_ms=5000)
    session = open_session(cfg)
    dispatcher = Dispatcher(session, tw.SERVICE, timeout_s=60.0, max_in_flight_per_worker=2)
    dispatcher.wait_for_workers(1, timeout=10)
    dispatcher.submit(tw.BusTestJob(text="long", spin_s=30))
    dispatcher.submit(tw.BusTestJob(text="queued behind it", spin_s=30))
    wait_until(lambda: worker.status().in_flight == 2, 5, "both jobs to reach the worker")
    gone_at = time.monotonic()
    session.close()  # the caller leaves without a word
    wait_until(lambda: worker.status().in_flight == 0, 5, "the caller's jobs to be cancelled")
    freed_after = time.monotonic() - gone_at
    with open_session(cfg) as other:
        assert send(other, key, tw.BusTestJob(text="next caller"))().text == "next caller"
    assert worker.status().jobs_done == 1  # the next caller's only: the cancelled jobs count as failed
    assert freed_after < 2.0, f"the worker was held {freed_after:.2f} s after its caller left"


def test_a_raw_query_without_a_caller_key_is_bounded_by_its_deadline_alone(client, serve):
    worker, key = serve("callers-2", job_deadline_s=0.5)
    answer = send(client, key, tw.BusTestJob(spin_s=30))()
    assert isinstance(answer, ErrorReply) and answer.code == "timeout", answer


# ---------------------------------------------------------------------------------------- sized budgets
def test_each_job_gets_the_budget_its_size_asks_for_within_the_worker_cap(client, serve):
    worker, key = serve("budget-1", job_budget=lambda job: 0.3 if job.text == "small" else 99.0, job_deadline_s=0.8)
    started = time.monotonic()
    small = send(client, key, tw.BusTestJob(text="small", spin_s=30))()
    assert isinstance(small, ErrorReply) and small.code == "timeout" and "deadline of 0.3 s" in small.message
    big = send(client, key, tw.BusTestJob(text="big", spin_s=30))()
    assert isinstance(big, ErrorReply) and big.code == "timeout" and "deadline of 0.8 s" in big.message  # capped
    assert time.monotonic() - started < 3.0


def test_a_small_job_runs_beside_a_big_one_on_the_express_thread(client, serve):
    worker, key = serve("express-1", concurrency=1, express=lambda job: job.text.startswith("small"))
    big = send(client, key, tw.BusTestJob(text="big", sleep_s=3.0))
    wait_until(lambda: worker.status().in_flight == 1, 2, "the big job to start")
    started = time.monotonic()
    small = send(client, key, tw.BusTestJob(text="small"))()
    assert small.text == "small" and time.monotonic() - started < 1.0, "the small job waited for the big one"
    other_big = send(client, key, tw.BusTestJob(text="second big"))  # not express: it waits its turn
    assert big().text == "big" and other_big().text == "second big"


def test_every_service_sizes_its_jobs_deadline_by_the_work_they_ask_for():
    """A bigger job gets a longer deadline, a small one a short one, and none the worker's hour by default."""
    import numpy as np

    from services.generator.service import job_budget as generation_budget
    from services.planner.service import job_budget as push_budget
    from shared.contracts.messages import (
        DirectionFrame,
        ObjectPose,
        PlannerOptions,
        PushRequest,
        SampleRequest,
        ValidationJob,
    )
    from shared.sampling.server import job_budget as sample_budget
    from shared.validation.jobs import JOB_DEADLINE_S
    from shared.validation.jobs import job_budget as validation_budget

    box = ObjectRef(library_id="proc-box-001")
    poses = lambda n: np.zeros((n, 25))  # noqa: E731
    one, many = (validation_budget(ValidationJob(object=box, hand="allegro", poses=poses(n))) for n in (1, 200))
    assert one < 60.0 < many and validation_budget(ValidationJob(object=box, hand="allegro", poses=poses(4096),
                                                                 augment=True)) == JOB_DEADLINE_S
    small, large = (generation_budget(GenerationJob(object=box, hand="allegro", batch_size=b, iterations=1500))
                    for b in (8, 1024))
    assert 60.0 < small < large < 3600.0
    frame = DirectionFrame(object_pose=ObjectPose(position=(0.4, 0.0, 0.0)), yaw_deg=0.0)
    assert sample_budget(SampleRequest(object=box, hand="allegro", frame=frame, k=10)) < sample_budget(
        SampleRequest(object=box, hand="allegro", frame=frame, k=1000, critic_guidance=0.02)) < 3600.0
    direction = PushRequest(object=box, direction_deg=0.0, options=PlannerOptions(corrections=0))
    corrected = PushRequest(object=box, direction_deg=0.0)  # the default: up to 2 corrective pushes
    goal = PushRequest(object=box, goal_xy=(0.5, 0.1))
    assert push_budget(direction) < push_budget(corrected) < push_budget(goal)

"""Bus benchmark: request round-trip latency through a router, and dispatcher throughput.

    python bench/bus.py --json [--jobs 4000] [--workers 1,2,4]

Everything runs as separate processes on loopback, as deployed: a router process (a Python
session in router mode, what `gd2p up` embeds), worker processes (`shared.bus.run_worker`) and this
client process. Measured:
- `rtt_raw_ms`: a 1 KB request message -> worker -> reply, one at a time, straight `session.get` on
  the worker's key (codec + validation on both sides included);
- `rtt_dispatcher_ms`: the same request through `Dispatcher.call`;
- `throughput_jobs_per_s`: no-op jobs pushed through `Dispatcher.map` with 1, 2, 4 worker processes.
The last line printed is a JSON object.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import socket
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

REPO_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO_DIR not in sys.path:
    sys.path.insert(0, REPO_DIR)

from shared.bus import BusConfig, Dispatcher, job_key, open_session, run_worker  # noqa: E402
from shared.contracts.codec import decode, encode  # noqa: E402
from shared.contracts.messages import Message  # noqa: E402

SERVICE = "busbench"


class BenchEcho(Message):
    """A request carrying `data`; the worker sends it back."""

    data: bytes = b""


class BenchNoop(Message):
    """The smallest job: only the id and schema version."""


class BenchDone(Message):
    """Reply to a no-op job."""


HANDLERS: dict[type[Message], Callable[[Any], Message]] = {BenchEcho: lambda job: BenchEcho(data=job.data), BenchNoop: lambda job: BenchDone()}


# ------------------------------------------------------------------------------------------ processes
def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serve_router(endpoint: str) -> None:
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with open_session(BusConfig(mode="router", listen=[endpoint], connect=[])):
        stop.wait()


def serve_worker(endpoint: str, worker_id: str) -> None:
    run_worker(SERVICE, HANDLERS, BusConfig(connect=[endpoint]), worker_id=worker_id)


def spawn(role: str, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, os.path.abspath(__file__), f"--serve-{role}", *args])


def stop(procs: list[subprocess.Popen]) -> None:
    for proc in procs:
        proc.terminate()
    for proc in procs:
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()


# ------------------------------------------------------------------------------------------ measurements
def percentiles(samples_s: list[float]) -> dict[str, float]:
    ms = sorted(s * 1e3 for s in samples_s)
    return {
        "p50": round(statistics.median(ms), 3),
        "p99": round(ms[min(len(ms) - 1, int(0.99 * len(ms)))], 3),
        "mean": round(statistics.fmean(ms), 3),
        "n": len(ms),
    }


def raw_round_trips(session, worker_id: str, n: int, size: int) -> list[float]:
    key = job_key(SERVICE, worker_id)
    samples = []
    for _ in range(n):
        t0 = time.perf_counter()
        job = BenchEcho(data=os.urandom(size))
        payload, encoding = encode(job)
        replies = list(session.get(key, payload=payload, encoding=encoding, timeout=10.0))
        reply = decode(replies[0].ok.payload.to_bytes(), str(replies[0].ok.encoding), BenchEcho)
        samples.append(time.perf_counter() - t0)
        assert isinstance(reply, BenchEcho) and reply.data == job.data and reply.id == job.id
    return samples


def dispatcher_round_trips(dispatcher: Dispatcher, n: int, size: int) -> list[float]:
    samples = []
    for _ in range(n):
        job = BenchEcho(data=os.urandom(size))
        t0 = time.perf_counter()
        reply = dispatcher.call(job, timeout=10.0)
        samples.append(time.perf_counter() - t0)
        assert isinstance(reply, BenchEcho) and reply.data == job.data
    return samples


def throughput(session, n_jobs: int, in_flight: int) -> float:
    with Dispatcher(session, SERVICE, max_in_flight_per_worker=in_flight, timeout_s=30.0) as dispatcher:
        dispatcher.wait_for_workers(1, timeout=30)
        list(dispatcher.map(BenchNoop() for _ in range(200)))  # warm-up
        jobs = [BenchNoop() for _ in range(n_jobs)]
        t0 = time.perf_counter()
        results = list(dispatcher.map(jobs))
        elapsed = time.perf_counter() - t0
    assert len(results) == n_jobs and all(isinstance(r, BenchDone) for r in results)
    return n_jobs / elapsed


def run(args: argparse.Namespace) -> dict:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = spawn("router", endpoint)
    workers: list[subprocess.Popen] = []
    result: dict = {"python": platform.python_version(), "cpus": os.cpu_count(), "request_bytes": args.size}
    try:
        with open_session(BusConfig(connect=[endpoint], connect_timeout_ms=30_000)) as session:
            with Dispatcher(session, SERVICE) as dispatcher:
                workers.append(spawn("worker", endpoint, "w0"))
                dispatcher.wait_for_workers(1, timeout=30)
                raw_round_trips(session, "w0", 100, args.size)  # warm-up
                result["rtt_raw_ms"] = percentiles(raw_round_trips(session, "w0", args.rtt, args.size))
                result["rtt_dispatcher_ms"] = percentiles(dispatcher_round_trips(dispatcher, args.rtt, args.size))
                rates = {}
                for count in args.workers:
                    while len(workers) < count:
                        workers.append(spawn("worker", endpoint, f"w{len(workers)}"))
                    dispatcher.wait_for_workers(count, timeout=30)
                    rates[str(count)] = round(throughput(session, args.jobs, args.in_flight), 1)
                result["throughput_jobs_per_s"] = rates
                result["in_flight_per_worker"] = args.in_flight
    finally:
        stop(workers + [router])
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true", help="print only the JSON result")
    parser.add_argument("--rtt", type=int, default=1000, help="round trips to time")
    parser.add_argument("--size", type=int, default=1024, help="request payload bytes")
    parser.add_argument("--jobs", type=int, default=4000, help="no-op jobs per throughput run")
    parser.add_argument("--workers", type=lambda s: [int(x) for x in s.split(",")], default=[1, 2, 4])
    parser.add_argument("--in-flight", type=int, default=8, help="dispatcher limit per worker")
    parser.add_argument("--serve-router", metavar="ENDPOINT", help=argparse.SUPPRESS)
    parser.add_argument("--serve-worker", nargs=2, metavar=("ENDPOINT", "ID"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve_router:
        serve_router(args.serve_router)
        return 0
    if args.serve_worker:
        serve_worker(*args.serve_worker)
        return 0
    result = run(args)
    if not args.json:
        print(f"round trip (raw get)   p50 {result['rtt_raw_ms']['p50']} ms  p99 {result['rtt_raw_ms']['p99']} ms")
        print(f"round trip (dispatcher) p50 {result['rtt_dispatcher_ms']['p50']} ms  p99 {result['rtt_dispatcher_ms']['p99']} ms")
        for count, rate in result["throughput_jobs_per_s"].items():
            print(f"throughput {count} worker(s): {rate} jobs/s")
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

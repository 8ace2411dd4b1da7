"""The Zenoh bus: session config, key expressions, worker runtime, discovery, dispatcher, recorded publishers.

    from shared.bus import BusConfig, open_session, run_worker, Dispatcher, live_workers
"""
from shared.bus.config import DEFAULT_ROUTER_ENDPOINT, MODES, BusConfig, open_session
from shared.bus.discovery import health, live_workers, worker_counts
from shared.bus.dispatcher import Dispatcher
from shared.bus.errors import BusError, DispatchError, OpenCancelled, RemoteError, RouterUnreachable
from shared.bus.keys import (
    ALL_KEYS,
    alive_key,
    alive_pattern,
    job_key,
    parse_alive_key,
    status_key,
    status_pattern,
)
from shared.bus.recorded import STREAM_QUEUE, RecordedPublisher, sequence_attachment, sequence_of
from shared.bus.worker import Worker, default_worker_id, run_worker

__all__ = [
    "ALL_KEYS", "DEFAULT_ROUTER_ENDPOINT", "MODES",
    "BusConfig", "open_session",
    "BusError", "DispatchError", "OpenCancelled", "RemoteError", "RouterUnreachable",
    "alive_key", "alive_pattern", "job_key", "parse_alive_key", "status_key", "status_pattern",
    "Worker", "default_worker_id", "run_worker",
    "STREAM_QUEUE", "RecordedPublisher", "sequence_attachment", "sequence_of",
    "health", "live_workers", "worker_counts", "Dispatcher",
]

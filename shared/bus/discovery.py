"""Who is alive on the bus: a liveliness query over `gd2p/alive/**`."""
from __future__ import annotations

import zenoh

from shared.bus.errors import BusError
from shared.bus.keys import PREFIX, alive_pattern, check_chunk, parse_alive_key
from shared.contracts.codec import CodecError, decode, encode
from shared.contracts.messages import HealthQuery, WorkerStatus


def live_workers(session: zenoh.Session, service: str | None = None, timeout: float = 1.0) -> dict[str, list[str]]:
    """{service: sorted worker ids} of every live worker (of `service` only, if given).

    Returns as soon as the router has answered (`timeout` bounds the wait, in seconds).
    Use a session without a liveliness subscriber (e.g. a CLI's own): with eclipse-zenoh 1.10.2 a
    client that also holds a liveliness subscriber was seen to get an empty answer for a while
    after declaring it. Where a `Dispatcher` runs, ask `Dispatcher.live()` instead.
    """
    workers: dict[str, set[str]] = {}
    for reply in session.liveliness().get(alive_pattern(service), timeout=timeout):
        if reply.ok is None:
            continue  # e.g. the query timed out: what arrived so far is the answer
        try:
            svc, worker_id = parse_alive_key(str(reply.ok.key_expr))
        except BusError:
            continue
        workers.setdefault(svc, set()).add(worker_id)
    return {svc: sorted(ids) for svc, ids in sorted(workers.items())}


def worker_counts(session: zenoh.Session, timeout: float = 1.0) -> dict[str, int]:
    """{service: number of live workers}: what `gd2p status --json` prints."""
    return {svc: len(ids) for svc, ids in live_workers(session, timeout=timeout).items()}


def health(session: zenoh.Session, service: str | None = None, timeout: float = 2.0) -> list[WorkerStatus]:
    """Ask every worker (of `service`, or of all services) for its `WorkerStatus`."""
    payload, encoding = encode(HealthQuery())
    selector = f"{PREFIX}/{check_chunk(service, 'service') if service else '*'}/worker/*/job"
    statuses = []
    replies = session.get(
        selector, payload=payload, encoding=encoding, target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout,
    )
    for reply in replies:
        if reply.ok is None:
            continue
        try:
            status = decode(reply.ok.payload.to_bytes(), str(reply.ok.encoding), WorkerStatus)
        except CodecError:
            continue  # something that is not one of our workers answered on this key
        if isinstance(status, WorkerStatus):  # not an ErrorReply (e.g. a worker shutting down)
            statuses.append(status)
    return sorted(statuses, key=lambda s: (s.service, s.worker_id))

"""Bus adapter of the planner service: push and pull requests: sampling, IK, planning, ranking (issue 6).

The algorithm arrives with issue 6. Until then a PushRequest gets a clear `not_implemented`
error reply — never a fake result — while the worker itself is real: it registers on the bus
and answers health queries. `handlers()` is the one place where the algorithm plugs in.
"""
from __future__ import annotations

from collections.abc import Callable

from shared.bus import ServiceError
from shared.messages import PushRequest, PushResponse, Message

SERVICE = "planner"


def push(request: PushRequest) -> PushResponse:
    """Plan, rank and execute a push of `request.object`."""
    raise ServiceError("not_implemented", "planner: PushRequest is not implemented yet (issue 6)")


def handlers() -> dict[type[Message], Callable[[Message], Message]]:
    """Message type -> handler, served by every planner worker."""
    return {PushRequest: push}

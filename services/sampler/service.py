"""Bus adapter of the sampler service: diffusion sampling of push poses (issue 9).

The algorithm arrives with issue 9. Until then a SampleRequest gets a clear `not_implemented`
error reply — never a fake result — while the worker itself is real: it registers on the bus
and answers health queries. `handlers()` is the one place where the algorithm plugs in.
"""
from __future__ import annotations

from collections.abc import Callable

from shared.bus import ServiceError
from shared.messages import SampleRequest, SampleResponse, Message

SERVICE = "sampler"


def sample(request: SampleRequest) -> SampleResponse:
    """Sample `request.k` push poses for `request.object` in its direction frame."""
    raise ServiceError("not_implemented", "sampler: SampleRequest is not implemented yet (issue 9)")


def handlers() -> dict[type[Message], Callable[[Message], Message]]:
    """Message type -> handler, served by every sampler worker."""
    return {SampleRequest: sample}

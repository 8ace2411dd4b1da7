"""Bus adapter of the generator service: energy-based synthesis of push poses (issue 4).

The algorithm arrives with issue 4. Until then a GenerationJob gets a clear `not_implemented`
error reply — never a fake result — while the worker itself is real: it registers on the bus
and answers health queries. `handlers()` is the one place where the algorithm plugs in.
"""
from __future__ import annotations

from collections.abc import Callable

from shared.bus import ServiceError
from shared.messages import GenerationJob, GenerationResult, Message

SERVICE = "generator"


def generate(job: GenerationJob) -> GenerationResult:
    """Optimise `job.batch_size` pre-contact push poses for `job.object` (paper Eq. 1)."""
    raise ServiceError("not_implemented", "generator: GenerationJob is not implemented yet (issue 4)")


def handlers() -> dict[type[Message], Callable[[Message], Message]]:
    """Message type -> handler, served by every generator worker."""
    return {GenerationJob: generate}

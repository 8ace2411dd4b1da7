"""Bus adapter of the validator service: PyBullet push validation (issue 5).

The algorithm arrives with issue 5. Until then a ValidationJob gets a clear `not_implemented`
error reply — never a fake result — while the worker itself is real: it registers on the bus
and answers health queries. `handlers()` is the one place where the algorithm plugs in.
"""
from __future__ import annotations

from collections.abc import Callable

from shared.bus import ServiceError
from shared.messages import ValidationJob, ValidationResult, Message

SERVICE = "validator"


def validate(job: ValidationJob) -> ValidationResult:
    """Push `job.object` with the hand at each pose of `job.poses` and judge the outcome."""
    raise ServiceError("not_implemented", "validator: ValidationJob is not implemented yet (issue 5)")


def handlers() -> dict[type[Message], Callable[[Message], Message]]:
    """Message type -> handler, served by every validator worker."""
    return {ValidationJob: validate}

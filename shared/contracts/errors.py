"""The error a service handler raises to answer with an `ErrorReply` code: part of the contract, not
of the bus, so algorithm modules raise it without loading Zenoh."""
from __future__ import annotations

from shared.contracts.messages import ErrorReply


class ServiceError(Exception):
    """Raised by a service handler to answer with a specific `ErrorReply` code.

    `code` must be one of `ErrorReply.CODES` (e.g. "infeasible", "not_implemented").
    """

    def __init__(self, code: str, message: str):
        if code not in ErrorReply.CODES:
            raise ValueError(f"ServiceError code {code!r} is not one of {', '.join(ErrorReply.CODES)}")
        super().__init__(message)
        self.code = code
        self.message = message

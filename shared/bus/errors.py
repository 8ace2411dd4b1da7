"""Exceptions of the bus layer."""
from __future__ import annotations

from shared.contracts.messages import ErrorReply


class BusError(RuntimeError):
    """Misconfiguration or misuse of the bus (bad mode, bad key chunk, closed dispatcher...)."""


class RouterUnreachable(BusError):
    """A client with a finite connect timeout found no router."""


class OpenCancelled(BusError):
    """The stop event was set while `open_session` was still waiting for a router."""


class RemoteError(Exception):
    """A worker answered with an `ErrorReply`; raised on the caller side (e.g. by `Dispatcher.call`)."""

    def __init__(self, reply: ErrorReply):
        where = f"{reply.service}: " if reply.service else ""
        super().__init__(f"{where}{reply.code}: {reply.message}")
        self.reply = reply
        self.code = reply.code
        self.message = reply.message


class DispatchError(Exception):
    """A job could not be delivered: no worker answered within `max_attempts`, or the dispatcher closed.

    `code` is "timeout" (attempts exhausted) or "unavailable" (dispatcher closed).
    """

    def __init__(self, code: str, message: str, job_id: str | None = None):
        super().__init__(message)
        self.code = code
        self.message = message
        self.job_id = job_id

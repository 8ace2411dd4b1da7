"""Python client of push requests: `push(request, cfg) -> PushResponse`.

The request goes to a planner worker through a Dispatcher; while it is served the client holds a
liveliness token (`gd2p/lease/client-<id>`), its lease: the client's session, and with it the token,
disappears if the client dies, which anyone watching the lease key (a supervisor, the recorder) sees.
The robot itself is commanded by the planner, under the planner's own lease.
"""
from __future__ import annotations

import uuid

from shared.bus import BusConfig, Dispatcher, RemoteError, open_session
from shared.bus.errors import DispatchError
from shared.bus.keys import LEASE_PREFIX
from shared.messages import PushRequest, PushResponse

DEFAULT_TIMEOUT_S = 600.0  # sampling, planning, rollouts and a simulated execution of up to 10 pushes


class PushFailed(Exception):
    """The planner could not serve the request; `code` is the ErrorReply code (e.g. "infeasible")."""

    def __init__(self, code: str, message: str):
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


def push(request: PushRequest, cfg: BusConfig, timeout_s: float = DEFAULT_TIMEOUT_S) -> PushResponse:
    """Send `request` to the planner and wait for its response; PushFailed when it cannot be served."""
    with open_session(cfg) as session:
        token = session.liveliness().declare_token(f"{LEASE_PREFIX}/client-{uuid.uuid4().hex[:12]}")
        try:
            with Dispatcher(session, "planner", timeout_s=timeout_s, max_attempts=1) as planner:
                try:
                    reply = planner.call(request, timeout=timeout_s + 5.0)
                except RemoteError as exc:
                    raise PushFailed(exc.code, exc.message) from exc
                except (DispatchError, TimeoutError) as exc:
                    raise PushFailed("unavailable", f"no planner answered within {timeout_s:.0f} s: {exc}") from exc
        finally:
            token.undeclare()
    if not isinstance(reply, PushResponse):
        raise PushFailed("internal", f"the planner answered with {type(reply).__name__}, not a PushResponse")
    return reply

"""Python client of push requests: `push(request, cfg) -> PushResponse`.

The request goes to a planner worker through a Dispatcher. While it is served the client holds its
lease, a liveliness token `gd2p/lease/client/<identity>/<id>` named in `PushRequest.client_lease` (its
identity: "cli" unless told, the CN of the certificate every push client carries in the secure
profile, whose rules let it declare tokens only under its own identity's part); the planner
watches it and cancels the request the moment it disappears: the client was interrupted (Ctrl-C
leaves the session, and with it the token), crashed, or lost its connection. A cancelled request
stops sampling and planning, and stops the robot if it moves.

The client watches the same lease from its side (`LeaseMonitor`: the router must confirm it every
50 ms). When it cannot, the connection is lost and nobody can tell the client whether the push
ran: `PushOutcomeUnknown`, never "unavailable". "unavailable" means no planner was there to ask.
"""
from __future__ import annotations

import time
import uuid
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout

from shared.bus import BusConfig, Dispatcher, open_session
from shared.bus.errors import DispatchError
from shared.bus.lease import LeaseMonitor, lease_key
from shared.contracts.messages import ErrorReply, Message, PushRequest, PushResponse

DEFAULT_TIMEOUT_S = 600.0  # sampling, planning, rollouts and a simulated execution of up to 10 pushes
PLANNER_WAIT_S = 5.0  # how long to wait for a live planner before saying there is none
_POLL_S = 0.05


class PushFailed(Exception):
    """The planner could not serve the request; `code` is the ErrorReply code (e.g. "infeasible")."""

    def __init__(self, code: str, message: str):
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


class PushOutcomeUnknown(PushFailed):
    """The connection was lost while the request was being served: it may or may not have run."""

    def __init__(self, message: str):
        super().__init__("outcome_unknown", message)


def push(request: PushRequest, cfg: BusConfig, timeout_s: float = DEFAULT_TIMEOUT_S,
         identity: str | None = None) -> PushResponse:
    """Send `request` to the planner and wait for its response; PushFailed when it cannot be served.

    Leaving early (KeyboardInterrupt, `timeout_s`) drops the lease, which cancels the request. `identity`:
    the one the lease key names (default "cli", LEASE_IDENTITIES); under the secure profile it must be the
    CN of `cfg`'s certificate: the router drops any other token, so the lease is never confirmed and the
    request is cancelled.
    """
    key = lease_key("client", uuid.uuid4().hex[:16], identity)  # a malformed identity fails before connecting
    with open_session(cfg) as session:
        token = session.liveliness().declare_token(key)
        try:
            with LeaseMonitor(session, key) as connection, \
                    Dispatcher(session, "planner", timeout_s=timeout_s, max_attempts=1) as planner:
                _wait_for_planner(planner)
                future = planner.submit(request.model_copy(update={"client_lease": key}))
                reply = _await(future, connection, timeout_s)
        finally:
            token.undeclare()
    if isinstance(reply, ErrorReply):
        raise PushFailed(reply.code, reply.message)
    if not isinstance(reply, PushResponse):
        raise PushFailed("internal", f"the planner answered with {type(reply).__name__}, not a PushResponse")
    return reply


def _wait_for_planner(planner: Dispatcher) -> None:
    try:
        planner.wait_for_workers(1, timeout=PLANNER_WAIT_S)
    except TimeoutError as exc:
        raise PushFailed("unavailable", f"no planner is running (none seen in {PLANNER_WAIT_S:.0f} s; is `gd2p up` "
                         "running and connected to the same router?)") from exc


def _await(future: Future[Message], connection: LeaseMonitor, timeout_s: float) -> Message:
    """The planner's reply; PushOutcomeUnknown once the connection is lost, PushFailed("timeout") after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        if connection.lost.is_set():
            raise PushOutcomeUnknown(
                f"lost the connection to the router while the request was served ({connection.reason}). The planner "
                "cancels the request and the robot stops when they notice this client is gone, but the push may "
                "already have run: look at the object before sending it again")
        if time.monotonic() > deadline:
            raise PushFailed("timeout", f"no answer within {timeout_s:.0f} s; the request is cancelled "
                             "(this client's lease is dropped, which stops the robot if it moves)")
        try:
            return future.result(timeout=_POLL_S)
        except FutureTimeout:
            continue
        except DispatchError as exc:
            raise PushOutcomeUnknown(f"the planner stopped answering while serving the request ({exc.message}); "
                                     "the push may or may not have run") from exc

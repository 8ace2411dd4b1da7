"""Confirm a plan the robot bridge holds (`gd2p up --confirm`): `confirm(session, command_id) -> PlanConfirmReply`.

With confirm on (the default with `--hardware`), the bridge holds each command that passed every check
before motion, publishes a `PlanHeld` on `gd2p/robot_bridge/held` (again every second while it waits, and
once more with `reason` set when the hold ends) and runs it only when an operator confirms it here,
within its timeout. The live view's button and `gd2p confirm ID` both call `confirm`.

Under the secure profile only the `operator` identity may query the confirm key: the router drops anyone
else's query, which then looks exactly like no bridge at all (`ConfirmError`).
"""
from __future__ import annotations

import threading
import time

import zenoh

from shared.bus.keys import ROBOT_CONFIRM_KEY, ROBOT_HELD_KEY
from shared.contracts.codec import CodecError, decode, encode
from shared.contracts.messages import ErrorReply, PlanConfirm, PlanConfirmReply, PlanHeld

HELD_REPEAT_S = 1.0  # the bridge republishes each held plan this often while it waits


class ConfirmError(Exception):
    """No bridge answered the confirmation (none runs with --confirm, or this identity may not confirm), or
    it answered with an error."""


def confirm(session: zenoh.Session, command_id: str, operator: str | None = None,
            timeout_s: float = 5.0) -> PlanConfirmReply:
    """Ask the robot bridge to run its held command `command_id`; `operator` is recorded with it.

    The reply says `accepted` (the plan runs now) or why not (`reason`: unknown id, expired, already
    confirmed, dropped). ConfirmError when no bridge answers within `timeout_s`.
    """
    payload, encoding = encode(PlanConfirm(command_id=command_id, operator=operator))
    replies = list(session.get(ROBOT_CONFIRM_KEY, payload=payload, encoding=encoding, timeout=timeout_s))
    answers = [r.ok for r in replies if r.ok is not None]
    if not answers:
        errors = [r.err.payload.to_bytes().decode(errors="replace") for r in replies if r.err is not None]
        detail = f" ({'; '.join(errors)})" if errors else ""
        raise ConfirmError(f"no robot bridge answered on {ROBOT_CONFIRM_KEY} within {timeout_s:g} s{detail}: is the "
                           "system running with --confirm (`gd2p up --confirm`, the default with --hardware), and, "
                           "under the secure profile, is this session the operator identity (only `operator` may "
                           "confirm)?")
    try:
        reply = decode(answers[0].payload.to_bytes(), str(answers[0].encoding))
    except CodecError as exc:
        raise ConfirmError(f"the robot bridge's answer could not be decoded: {exc}") from exc
    if isinstance(reply, ErrorReply):
        raise ConfirmError(f"the robot bridge refused the confirmation ({reply.code}): {reply.message}")
    if not isinstance(reply, PlanConfirmReply):
        raise ConfirmError(f"the robot bridge answered with {type(reply).__name__}, not a PlanConfirmReply")
    return reply


def held_plans(session: zenoh.Session, wait_s: float = HELD_REPEAT_S * 1.5) -> list[PlanHeld]:
    """The plans the bridge holds now: every `PlanHeld` heard on the held key for `wait_s` (the bridge
    republishes each held plan every HELD_REPEAT_S), without those whose hold ended meanwhile; by expiry."""
    latest: dict[str, PlanHeld] = {}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            held = decode(sample.payload.to_bytes(), str(sample.encoding), PlanHeld)
        except CodecError:
            return
        if isinstance(held, PlanHeld):
            with lock:
                latest[held.command_id] = held

    subscriber = session.declare_subscriber(ROBOT_HELD_KEY, on_sample)
    try:
        time.sleep(wait_s)
    finally:
        subscriber.undeclare()
    with lock:
        waiting = [h for h in latest.values() if h.reason is None and h.expires_at > time.time()]
    return sorted(waiting, key=lambda h: h.expires_at)

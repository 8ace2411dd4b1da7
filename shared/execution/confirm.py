"""Preview and confirm (`gd2p up --confirm`): a command that passed every check before motion waits for an operator.

`ConfirmGate.hold` is the executor's hold step (`Executor(hold=...)`): called after `Executor.check` (the
e-stop, the world, the limits, the start state, the lease: all passed) and before anything moves. It
announces a `PlanHeld` (through `announce`; the bus adapter publishes it on gd2p/robot_bridge/held, and
again every `repeat_s` while it waits, so a view or `gd2p confirm --list` that starts late sees it), then
waits up to `timeout_s` for `ConfirmGate.confirm(PlanConfirm)`. While it waits the rules of motion hold
unchanged: a lost lease or an engaged e-stop drops the command at once (SafetyRefusal "lease" / "estop");
no confirmation within the timeout refuses it (SafetyRefusal "not_confirmed": the planner's push answers
ErrorReply "not_confirmed" and does not retry). Nothing moves in any of these cases. Every hold ends with
one more `PlanHeld` whose `reason` says how ("confirmed by ...", "expired ...", "dropped: ...").

A confirmation is accepted only for a command held now and not past its expiry; one for an unknown id, an
expired, dropped or already confirmed one is answered `accepted=False` with the reason. No bus here: the
bus side is services/robot_bridge/bus_safety.py (`ConfirmServer`).
"""
from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, Protocol

from shared.contracts.messages import ExecutionCommand, PlanConfirm, PlanConfirmReply, PlanHeld
from shared.execution.limits import SafetyRefusal

log = logging.getLogger("gd2p.robot_bridge.confirm")

DEFAULT_TIMEOUT_S = 60.0
MAX_TIMEOUT_S = 240.0  # the planner waits 300 s for a command's answer: the hold and the motion must fit
REPEAT_S = 1.0  # a held plan is announced again this often while it waits
POLL_S = 0.02  # how often a waiting hold looks at the e-stop
NOT_CONFIRMED = "not_confirmed"  # the SafetyRefusal check of an expired hold (and the planner's ErrorReply code)
REMEMBERED = 4096  # ended holds kept to answer a late confirmation with why

HoldState = Literal["held", "confirmed", "expired", "dropped"]


class _Latch(Protocol):
    @property
    def engaged(self) -> bool: ...

    @property
    def reason(self) -> str: ...


class _Lease(Protocol):
    @property
    def lost(self) -> bool: ...

    @property
    def reason(self) -> str: ...

    def on_lost(self, callback: Callable[[], None]) -> None: ...


@dataclass
class _Hold:
    held: PlanHeld
    state: HoldState = "held"
    why: str = ""
    operator: str | None = None
    wake: threading.Event = field(default_factory=threading.Event)


class ConfirmGate:
    """The held commands of one bridge and their confirmations (thread-safe)."""

    def __init__(self, estop: _Latch, timeout_s: float = DEFAULT_TIMEOUT_S,
                 announce: Callable[[PlanHeld], None] | None = None, repeat_s: float = REPEAT_S):
        if not 0.0 < timeout_s <= MAX_TIMEOUT_S:
            raise ValueError(f"the confirmation timeout must be in (0, {MAX_TIMEOUT_S:g}] s, not {timeout_s:g}")
        self.estop = estop
        self.timeout_s = timeout_s
        self.announce = announce
        self.repeat_s = repeat_s
        self._holds: OrderedDict[str, _Hold] = OrderedDict()
        self._lock = threading.Lock()

    # ------------------------------------------------------------------------------ the executor's side
    def hold(self, command: ExecutionCommand, lease: _Lease) -> str:
        """Wait for an operator's confirmation of `command`; who confirmed (or "" if unnamed). SafetyRefusal
        ("not_confirmed", "lease", "estop") when the hold ends any other way: then nothing may move."""
        held = PlanHeld(command_id=command.id, plan=command.plan, expires_at=time.time() + self.timeout_s)
        deadline = time.monotonic() + self.timeout_s
        entry = _Hold(held)
        with self._lock:
            self._holds[command.id] = entry
            self._holds.move_to_end(command.id)
            while len(self._holds) > REMEMBERED:
                oldest = next(iter(self._holds))
                if self._holds[oldest].state == "held":
                    break
                self._holds.popitem(last=False)
        lease.on_lost(entry.wake.set)
        log.warning("command %s held until an operator confirms it (gd2p confirm %s), %g s at most",
                    command.id, command.id, self.timeout_s)
        self._announce(held)
        next_announce = time.monotonic() + self.repeat_s
        refusal: SafetyRefusal | None = None
        while True:
            now = time.monotonic()
            with self._lock:
                if entry.state == "confirmed":
                    break
                if lease.lost:
                    refusal = SafetyRefusal("lease", f"the lease was lost while the plan waited for confirmation "
                                            f"({lease.reason}); nothing moved")
                elif self.estop.engaged:
                    refusal = SafetyRefusal("estop", f"e-stop while the plan waited for confirmation "
                                            f"({self.estop.reason}); nothing moved")
                elif now >= deadline:
                    refusal = SafetyRefusal(NOT_CONFIRMED, f"no operator confirmed command {command.id} within "
                                            f"{self.timeout_s:g} s (gd2p confirm ID, or the live view's button); "
                                            "the plan was dropped and nothing moved")
                if refusal is not None:
                    entry.state = "expired" if refusal.check == NOT_CONFIRMED else "dropped"
                    entry.why = (f"expired: not confirmed within {self.timeout_s:g} s" if entry.state == "expired"
                                 else f"dropped: {refusal}")
                    break
            if now >= next_announce:
                self._announce(held)
                next_announce = now + self.repeat_s
            entry.wake.wait(max(0.0, min(POLL_S, deadline - now)))
        self._announce(held.model_copy(update={"reason": entry.why}))
        if refusal is not None:
            log.warning("held command %s %s", command.id, entry.why)
            raise refusal
        log.warning("held command %s %s", command.id, entry.why)
        return entry.operator or ""

    # ------------------------------------------------------------------------------ the operator's side
    def confirm(self, request: PlanConfirm) -> PlanConfirmReply:
        """Release the held command `request.command_id` (accepted) or say why not."""
        command_id = request.command_id
        with self._lock:
            entry = self._holds.get(command_id)
            if entry is None:
                why = f"unknown command {command_id}: this bridge holds no such plan (see gd2p confirm --list)"
            elif entry.state == "confirmed":
                why = f"command {command_id} was already confirmed (by {entry.operator or 'an unnamed operator'})"
            elif entry.state == "expired" or (entry.state == "held" and time.time() >= entry.held.expires_at):
                why = f"command {command_id} expired: it was not confirmed within {self.timeout_s:g} s and was dropped"
            elif entry.state == "dropped":
                why = f"command {command_id} is no longer held ({entry.why})"
            else:
                entry.state = "confirmed"
                entry.operator = request.operator
                entry.why = f"confirmed by {request.operator or 'an unnamed operator'}"
                entry.wake.set()
                log.warning("command %s %s", command_id, entry.why)
                return PlanConfirmReply(command_id=command_id, accepted=True, reason=entry.why)
        return PlanConfirmReply(command_id=command_id, accepted=False, reason=why)

    def held(self) -> list[PlanHeld]:
        """The plans waiting now."""
        with self._lock:
            return [e.held for e in self._holds.values() if e.state == "held"]

    def _announce(self, held: PlanHeld) -> None:
        if self.announce is None:
            return
        try:
            self.announce(held)
        except Exception:  # a view that cannot be told must not change what the robot does
            log.exception("could not announce held command %s", held.command_id)

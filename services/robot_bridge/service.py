"""Bus adapter of the robot_bridge service: plan execution on the robot (issues 6, 7).

The simulated backend arrives with issue 6, the hardware adapters with issue 7. Until then an
ExecutionCommand gets a clear `not_implemented` error reply — never a fake result — while the
worker itself is real: it registers on the bus and answers health queries. `handlers()` is the
one place where the algorithm plugs in.
"""
from __future__ import annotations

from collections.abc import Callable

from shared.bus import ServiceError
from shared.messages import ExecutionCommand, ExecutionState, Message

SERVICE = "robot_bridge"


def execute(command: ExecutionCommand) -> ExecutionState:
    """Execute `command.plan` on the robot and report the final state."""
    raise ServiceError("not_implemented", "robot_bridge: ExecutionCommand is not implemented yet (issue 6)")


def handlers() -> dict[type[Message], Callable[[Message], Message]]:
    """Message type -> handler, served by every robot_bridge worker."""
    return {ExecutionCommand: execute}

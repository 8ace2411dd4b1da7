"""What a push request produces: its response with the executed steps, or the error with those it executed.

`PushPipeline.run` returns a `PushOutcome` (the response and one `StepRecord` per executed push, for
the recording and the evaluation); a request that cannot be served raises `PushError`, whose
`records` are the pushes it executed before it failed (a multi-step request may have moved the
object several times first).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from shared.contracts.messages import ExecutionState, PushResponse, PushStep, SimWorld


@dataclass
class Execution:
    """What the robot bridge reports for one executed plan: its final state and the states on the way."""

    final: ExecutionState
    states: list[ExecutionState] = field(default_factory=list)


@dataclass
class StepRecord:
    """Everything about one executed push, for the response and the recording."""

    step: PushStep
    T_world_O_start: np.ndarray
    execution: Execution
    world: SimWorld | None  # the world the bridge was reset to before this push (None: it went on from the last)


@dataclass
class PushOutcome:
    """A served request: the response, and a record of every push executed for it (in order)."""

    response: PushResponse
    records: list[StepRecord]


class PushError(Exception):
    """A push request that cannot be served; `code` is an ErrorReply code (infeasible, bad_request, ...).

    `records`: the pushes executed for the request before it failed (empty unless a multi-step
    request moved the object before getting stuck).
    """

    def __init__(self, code: str, message: str, records: Sequence[StepRecord] = ()):
        super().__init__(message)
        self.code = code
        self.message = message
        self.records: list[StepRecord] = list(records)

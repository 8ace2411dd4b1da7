"""Re-decide a recorded push (`gd2p replay FILE.mcap --resim`): plan its request again in process, compare.

A push recording (services/planner/recording.py) holds the request (with its capture, when the object came
as a point cloud), the response with the plan of every push it executed, and the `gd2p.decision` metadata
(shared/planning/decision.py: commit, models, seeds, settings). `resim` runs the request through the
evaluation's in-process system (`local_system.LocalSystem`: the sampler service's handler, the validator's
rollouts and the simulated robot behind the safety executor, the same pipeline as the planner service) and
compares each push's plan with the recorded one bit for bit. At the same commit, models and settings it
should come out identical; a different context is reported as a warning, and the request is planned anyway.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from shared.contracts.codec import CodecError
from shared.contracts.messages import Plan, PushRequest, PushResponse
from shared.planning.decision import METADATA_NAME, REQUIRED, Mismatch, compare_plans, context_mismatches
from shared.planning.outcome import PushError
from shared.planning.stages import PipelineSettings
from shared.sampling.models import model_ids
from visualisation.recording import RecordingError, read_metadata, read_records

REQUEST_KEY = "gd2p/planner/request"
RESPONSE_KEY = "gd2p/planner/response"


class UnusableRecording(Exception):
    """The file is not a push recording `resim` can plan again (not MCAP, or no request / response in it)."""


@dataclass
class ResimResult:
    path: Path
    request: PushRequest
    recorded: list[Plan]  # the plan of every push the recording executed
    replanned: list[Plan] = field(default_factory=list)
    differences: list[str] = field(default_factory=list)  # [] and a replanned plan per push: identical
    warnings: list[str] = field(default_factory=list)  # missing metadata, another commit, other models ...
    mismatches: list[Mismatch] = field(default_factory=list)

    @property
    def identical(self) -> bool:
        return not self.differences and len(self.replanned) == len(self.recorded)


def read_push_recording(path: str | Path) -> tuple[PushRequest, PushResponse, dict[str, str] | None]:
    """The request, the response and the `gd2p.decision` metadata (None if absent) of a push recording."""
    path = Path(path)
    if not path.is_file():
        raise UnusableRecording(f"no such recording: {path}")
    request = response = None
    try:
        for record in read_records(str(path)):
            if record.key not in (REQUEST_KEY, RESPONSE_KEY):
                continue
            try:
                message = record.decode()
            except CodecError as exc:
                raise UnusableRecording(f"{path}: its {record.key} message cannot be decoded: {exc}") from exc
            if record.key == REQUEST_KEY and isinstance(message, PushRequest):
                request = message
            elif record.key == RESPONSE_KEY and isinstance(message, PushResponse):
                response = message
        metadata = read_metadata(str(path)).get(METADATA_NAME)
    except RecordingError as exc:
        raise UnusableRecording(str(exc)) from exc
    if request is None:
        raise UnusableRecording(f"{path}: no PushRequest on {REQUEST_KEY}: not a push recording (the planner writes "
                                "one per push, push-<id>.mcap; the recorder's bus recordings are not re-decided)")
    if response is None:
        raise UnusableRecording(f"{path}: no PushResponse on {RESPONSE_KEY}: the recording has no decision to compare")
    return request, response, metadata


def executed_plans(response: PushResponse) -> list[Plan]:
    return [step.plan for step in response.steps] or [response.plan]


def resim(path: str | Path, settings: PipelineSettings | None = None) -> ResimResult:
    """Plan the recorded request again in this process and compare its plans with the recorded ones."""
    from evaluation.local_system import LocalSystem

    request, response, decision = read_push_recording(path)
    settings = settings or PipelineSettings()
    result = ResimResult(Path(path), request, executed_plans(response))
    if decision is None:
        result.warnings.append(f"no {METADATA_NAME} metadata (recorded before recordings carried the commit, models "
                               "and seeds): planning with this checkout's, which may differ")
    else:
        absent = [key for key in REQUIRED if key not in decision]
        if absent:
            result.warnings.append(f"the {METADATA_NAME} metadata lacks {', '.join(absent)}")
        result.mismatches = context_mismatches(decision, request, settings, model_ids(request.hand))
        result.warnings += [f"other {m}: the plan may differ for that reason alone" for m in result.mismatches]
    system = LocalSystem(settings)
    try:
        outcome = system.pipeline("sampler").run(request)
    except PushError as exc:
        result.differences.append(f"planning again failed ({exc.code}: {exc.message}); the recording executed "
                                  f"{len(result.recorded)} push(es)")
        return result
    finally:
        system.close()
    result.replanned = executed_plans(outcome.response)
    if len(result.replanned) != len(result.recorded):
        result.differences.append(f"{len(result.replanned)} push(es) planned again, {len(result.recorded)} recorded")
    for i, (recorded, replanned) in enumerate(zip(result.recorded, result.replanned, strict=False)):
        result.differences += [f"push {i + 1}: {d}" for d in compare_plans(recorded, replanned)]
    return result

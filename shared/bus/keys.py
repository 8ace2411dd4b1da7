"""Every key expression the system uses, in one place.

    gd2p/alive/<service>/<worker_id>             liveliness token of a worker
    gd2p/<service>/worker/<worker_id>/job        the worker's queryable (jobs and health queries)
    gd2p/status/<service>/<worker_id>            WorkerStatus heartbeat (~2 s), captured by the recorder
    gd2p/robot_bridge/command/execute            ExecutionCommand queries (only the planner may send them)
    gd2p/robot_bridge/state                      ExecutionState stream of the robot
    gd2p/robot_bridge/estop                      EStop: stop every robot backend
    gd2p/lease/<commander id>                    a commander's liveliness token (the command's lease)
"""
from __future__ import annotations

from shared.bus.errors import BusError

PREFIX = "gd2p"
ALIVE_PREFIX = f"{PREFIX}/alive"
STATUS_PREFIX = f"{PREFIX}/status"
ALL_KEYS = f"{PREFIX}/**"
ROBOT_COMMAND_KEY = f"{PREFIX}/robot_bridge/command/execute"
ROBOT_STATE_KEY = f"{PREFIX}/robot_bridge/state"
ROBOT_ESTOP_KEY = f"{PREFIX}/robot_bridge/estop"
LEASE_PREFIX = f"{PREFIX}/lease"
_FORBIDDEN = set("/*$?#")


def check_chunk(value: str, what: str) -> str:
    """A service name or worker id must be one non-empty key chunk without wildcards."""
    if not isinstance(value, str) or not value or _FORBIDDEN.intersection(value):
        raise BusError(f"invalid {what} {value!r}: must be non-empty and contain none of / * $ ? #")
    return value


def alive_key(service: str, worker_id: str) -> str:
    return f"{ALIVE_PREFIX}/{check_chunk(service, 'service')}/{check_chunk(worker_id, 'worker id')}"


def alive_pattern(service: str | None = None) -> str:
    """Liveliness tokens of every worker of `service` (or of every service)."""
    return f"{ALIVE_PREFIX}/{check_chunk(service, 'service') if service else '*'}/*"


def parse_alive_key(key: str) -> tuple[str, str]:
    """'gd2p/alive/validator/w1' -> ('validator', 'w1')."""
    parts = str(key).split("/")
    if len(parts) != 4 or f"{parts[0]}/{parts[1]}" != ALIVE_PREFIX:
        raise BusError(f"not a liveliness key: {key!r}")
    return parts[2], parts[3]


def job_key(service: str, worker_id: str) -> str:
    return f"{PREFIX}/{check_chunk(service, 'service')}/worker/{check_chunk(worker_id, 'worker id')}/job"


def status_key(service: str, worker_id: str) -> str:
    return f"{STATUS_PREFIX}/{check_chunk(service, 'service')}/{check_chunk(worker_id, 'worker id')}"


def status_pattern(service: str | None = None) -> str:
    return f"{STATUS_PREFIX}/{check_chunk(service, 'service') if service else '*'}/*"

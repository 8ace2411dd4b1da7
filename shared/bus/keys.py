"""The key expressions of the bus, as constants and builders, so that each key is spelled once.

    gd2p/alive/<service>/<worker_id>             liveliness token of a worker        alive_key, alive_pattern
    gd2p/<service>/worker/<worker_id>/job        the worker's queryable              job_key
    gd2p/status/<service>/<worker_id>            WorkerStatus heartbeat              status_key, status_pattern
    gd2p/robot_bridge/command/execute            ExecutionCommand queries            ROBOT_COMMAND_KEY
    gd2p/robot_bridge/state                      ExecutionState stream               ROBOT_STATE_KEY
    gd2p/robot_bridge/estop                      EStop                               ROBOT_ESTOP_KEY
    gd2p/robot_bridge/object_track               ObjectTrack stream                  OBJECT_TRACK_KEY
    gd2p/robot_bridge/held                       PlanHeld (--confirm)                ROBOT_HELD_KEY
    gd2p/robot_bridge/confirm                    PlanConfirm queries (--confirm)     ROBOT_CONFIRM_KEY
    gd2p/planner/decision                        PushDecision (live view)            PLANNER_DECISION_KEY
    gd2p/lease/<role>/<holder>                   a lease token (lease.py)            LEASE_PREFIX
    gd2p/watchdog/<name>                         router watchdog beats (lease.py)    WATCHDOG_PREFIX
    gd2p/caller/<id>                             a Dispatcher's presence (jobs)      CALLER_PREFIX, caller_key

Which message travels on each key, who declares it and who calls it: the interface registry,
shared/bus/interfaces.py, which builds its table from these. The one key outside the runtime, the
launcher's control key `gd2p/launcher/control`, is spelled there (`LAUNCHER_CONTROL_KEY`);
docs/interfaces.md is generated from the registry.
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
OBJECT_TRACK_KEY = f"{PREFIX}/robot_bridge/object_track"
ROBOT_HELD_KEY = f"{PREFIX}/robot_bridge/held"
ROBOT_CONFIRM_KEY = f"{PREFIX}/robot_bridge/confirm"
PLANNER_DECISION_KEY = f"{PREFIX}/planner/decision"  # in the planner's namespace: only the planner publishes
LEASE_PREFIX = f"{PREFIX}/lease"
WATCHDOG_PREFIX = f"{PREFIX}/watchdog"
CALLER_PREFIX = f"{PREFIX}/caller"
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


def caller_key(caller_id: str) -> str:
    """`gd2p/caller/<id>`: the liveliness token a Dispatcher holds while its jobs may run (worker.py Callers)."""
    return f"{CALLER_PREFIX}/{check_chunk(caller_id, 'caller id')}"

"""The interface registry: every key expression of the bus, what travels on it, who declares it, who calls it.

`INTERFACES` is one table of `Interface` rows, built from the key builders of shared/bus/keys.py (a key
is spelled there and nowhere else, the launcher's control key aside: `LAUNCHER_CONTROL_KEY` below) and
the models of shared/contracts/messages.py. A row says
- `key`: the key expression, `<name>` marking a chunk that varies (`pattern` turns each into `*`);
- `kind`: "queryable" (queried with `get`, answered with replies), "publication" (put, subscribed to)
  or "liveliness" (a token, watched with liveliness subscribers and queries);
- `declarers`: who may serve the queryable / publish / hold the token; `callers`: who may query it /
  subscribe / watch the token. Both name identities of the secure profile (`PARTICIPANTS`, one
  certificate each: deploy/secure/certs.py). deploy/secure/profile.py takes its tables (worker services,
  who calls whom, lease holders, keys anyone may put on) from here; tests/test_interfaces.py checks
  every row against the access rules that result, both ways;
- `exchanges` (request -> possible replies) or `message` (what is published), `used_by` (who does it in
  this code base), liveliness and QoS notes, and the code that declares and calls it.

docs/interfaces.md is generated from this module (a test keeps the committed file equal to it):

    python -m shared.bus.interfaces --markdown > docs/interfaces.md
"""
from __future__ import annotations

import argparse
import inspect
import json
import re
import sys
import types
import typing
from dataclasses import dataclass
from typing import Literal

import annotated_types
import zenoh
from pydantic import AfterValidator, BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from shared.bus import keys
from shared.bus.lease import BEAT_BYTES, BEAT_FORMAT, LEASE_ROLES, lease_key
from shared.contracts import messages
from shared.contracts.codec import ENCODING_PREFIX
from shared.contracts.messages import (
    SCHEMA_VERSION,
    ErrorReply,
    EStop,
    ExecutionCommand,
    ExecutionState,
    GenerationJob,
    GenerationResult,
    HealthQuery,
    Message,
    ObjectTrack,
    PlanConfirm,
    PlanConfirmReply,
    PlanHeld,
    PushDecision,
    PushRequest,
    PushResponse,
    SampleRequest,
    SampleResponse,
    ScaleReply,
    ScaleRequest,
    ValidationJob,
    ValidationResult,
    WorkerStatus,
)

Kind = Literal["queryable", "publication", "liveliness"]
LAUNCHER_CONTROL_KEY = f"{keys.PREFIX}/launcher/control"  # served by deploy/launcher.py
WORKER_ID = "<worker_id>"
WATCHDOG_KEY = f"{keys.WATCHDOG_PREFIX}/<name>"  # the router watchdog's beats (shared/bus/lease.py RouterWatchdog)
GENERATED_BY = "python -m shared.bus.interfaces --markdown > docs/interfaces.md"


@dataclass(frozen=True)
class Exchange:
    """One query a queryable answers: a `request` message and the messages it may be answered with."""

    request: type[Message]
    replies: tuple[type[Message], ...]


@dataclass(frozen=True)
class Service:
    """A service whose workers run the worker runtime (shared/bus/worker.py)."""

    name: str
    summary: str
    jobs: tuple[Exchange, ...]  # what its job key accepts besides HealthQuery
    callers: frozenset[str]  # who sends it jobs or health queries, besides its own healthcheck
    scalable: bool  # stateless job server (the launcher scales it) or a singleton
    used_by: str
    qos: str
    code: tuple[str, ...]

    @property
    def exchanges(self) -> tuple[Exchange, ...]:
        """Every query its job key answers: the runtime's HealthQuery, then the service's jobs."""
        return (Exchange(HealthQuery, (WorkerStatus, ErrorReply)), *self.jobs)


@dataclass(frozen=True)
class Interface:
    """One key expression of the bus (see the module docstring)."""

    title: str
    key: str
    kind: Kind
    summary: str
    declarers: frozenset[str]
    callers: frozenset[str]
    exchanges: tuple[Exchange, ...] = ()
    message: type[Message] | None = None
    payload: str = ""  # what travels when it is not a message
    used_by: str = ""
    liveliness: str = ""
    qos: str = ""
    code: tuple[str, ...] = ()
    service: str | None = None  # the service whose workers declare it (worker keys only)

    @property
    def pattern(self) -> str:
        """The key expression with every `<name>` chunk replaced by `*`: all instances of the key."""
        return re.sub(r"<[^/]+>", "*", self.key)

    def sample_key(self, chunk: str = "w-1") -> str:
        """A concrete instance of the key: every `<name>` chunk replaced by `chunk`."""
        return re.sub(r"<[^/]+>", chunk, self.key)

    def includes(self, key: str) -> bool:
        """True if the concrete key `key` is an instance of this row's key."""
        included: bool = zenoh.KeyExpr(self.pattern).includes(zenoh.KeyExpr(key))
        return included

    def messages(self) -> tuple[type[Message], ...]:
        """Every message type travelling on the key, requests first."""
        found = [self.message] if self.message else []
        found += [e.request for e in self.exchanges] + [r for e in self.exchanges for r in e.replies]
        return tuple(dict.fromkeys(found))


# ------------------------------------------------------------------------------------------ participants
# What every worker's keys have in common (shared/bus/worker.py), whatever its service.
_ALIVE_USED_BY = ("Dispatchers of the service's jobs (liveliness subscriber on `gd2p/alive/<service>/*`, history=True);"
                  " `gd2p status` and `live_workers` (liveliness query); the launcher's `wait_ready`.")
_ALIVE_LIVELINESS = ("Declared when the worker starts serving; undeclared first when it stops (before it drains its"
                     " jobs); the router drops it when the worker's session ends.")
_JOB_LIVELINESS = ("Served while the worker's token `gd2p/alive/<service>/<worker_id>` exists; a query that still"
                   " arrives while the worker stops is answered ErrorReply \"unavailable\" (a dispatcher sends it elsewhere).")
_JOB_QOS = ("Declared complete=True. A caller addresses one worker's key with consolidation NONE and attaches"
            " `{\"timeout_s\": T}` (a msgpack map) so the worker answers ErrorReply \"timeout\" just before T instead"
            " of working on for nobody; the reply comes back on the same key. `gd2p health` asks"
            " `gd2p/<service>/worker/*/job` with target ALL and consolidation NONE (5 s by default); a worker's own"
            " identity may query its key too (its container healthcheck, `gd2p health --this-host`).")
_RECORDED_QOS = ("Congestion control BLOCK (a full queue makes the publisher wait; Zenoh's default drops) and a"
                 " sequence attachment on every sample, msgpack `{\"publisher\": <id>, \"seq\": <n from 1>}`: the"
                 " recorder counts per key and publisher what it received and the gaps (missing) into each MCAP's"
                 " metadata (shared/bus/recorded.py: RecordedPublisher).")
_STATUS_QOS = ("About every 2 s and once more when the worker stops; best effort (a heartbeat that cannot be sent,"
               f" without a router, is skipped). {_RECORDED_QOS} Sent from a queue of 8, so the worker never waits.")
WORKERS: tuple[Service, ...] = (
    Service("generator", "energy-based synthesis of pre-contact hand poses (paper Eq. 1)",
            (Exchange(GenerationJob, (GenerationResult, ErrorReply)),), frozenset({"cli"}), True,
            "The data engine (`gd2p dataset build`, cli) through a Dispatcher; `gd2p generate` runs locally.",
            "A job may take up to the worker's deadline (1 h by default: a data-engine batch).",
            ("services/generator/service.py: handlers()", "cli/dataset.py: Dispatcher")),
    Service("validator", "PyBullet push validation farm + Halton augmentation; arm rollouts for ranking",
            (Exchange(ValidationJob, (ValidationResult, ErrorReply)),), frozenset({"planner", "cli"}), True,
            "The planner's Dispatcher (arm rollouts of ranked plans); `gd2p dataset build` (cli).",
            "The planner waits 120 s per rollout and sends at most one job at a time to each validator.",
            ("shared/validation/jobs.py: handlers()", "services/planner/service.py: BusServices.validate")),
    Service("sampler", "BPS-conditioned diffusion model (DDPM-100 / DDIM fast path), NN baseline",
            (Exchange(SampleRequest, (SampleResponse, ErrorReply)),), frozenset({"planner", "cli"}), True,
            "The planner's Dispatcher (candidate poses of a push); `gd2p sample` runs locally.",
            "The planner waits 60 s for a SampleResponse.",
            ("shared/sampling/server.py: handlers()", "services/planner/service.py: BusServices.sample")),
    Service("planner", "push/pull requests: IK, RRTConnect, rollouts, ranking, multi-step",
            (Exchange(PushRequest, (PushResponse, ErrorReply)),), frozenset({"cli"}), True,
            "`gd2p push`, `gd2p demo` and the Python push client (client/push_client.py), through a Dispatcher"
            " with one attempt; examples/raw_zenoh_push.py (zenoh + msgpack only).",
            "One push at a time per planner (one robot). The push client waits up to 600 s. A request naming"
            " `client_lease` is cancelled (ErrorReply \"cancelled\") when that lease token disappears.",
            ("services/planner/service.py: PlannerService.handlers", "client/push_client.py: push")),
    Service("robot_bridge", "executes plans: simulated robot (default), panda (Franka FR3) / xarm7 / leap / allegro robots",
            (Exchange(EStop, (ExecutionState, ErrorReply)),), frozenset({"cli"}), False,
            "Health queries (cli); an EStop job stops every robot like the e-stop key. Commands do not come"
            " here (anyone could query this key): they go to `gd2p/robot_bridge/command/execute`.",
            "The EStop job's reply is the state of the first robot it stopped.",
            ("services/robot_bridge/service.py: Bridge.handlers",)),
    Service("recorder", "writes every gd2p/** publication to MCAP (zstd, rotating)", (), frozenset({"cli"}), False,
            "Health queries only (cli, and its container healthcheck).",
            "None beyond every worker's.",
            ("services/recorder/service.py: RecorderService.run",)),
)
SERVICES: tuple[str, ...] = tuple(s.name for s in WORKERS)
SCALABLE: frozenset[str] = frozenset(s.name for s in WORKERS if s.scalable)
TOOLS: dict[str, str] = {
    "launcher": "`gd2p up` (deploy/launcher.py): the embedded router and the supervisor of every service process",
    "cli": "the operator's everyday tools: `gd2p push/generate/validate/sample/dataset/status/health`, "
           "`gd2p bridge estop`, the Python push client, examples/raw_zenoh_push.py",
    "operator": "host administration: `deploy/scale_validators.py` (the launcher's control key)",
    "tracker": "a user's object tracker next to real hardware (RGB-D pose tracker, markers, motion capture): "
               "publishes the object's pose while the robot pushes it",
}
PARTICIPANTS: dict[str, str] = {s.name: f"service: {s.summary}" for s in WORKERS} | TOOLS
EVERYONE: frozenset[str] = frozenset(PARTICIPANTS)
# Lease role (shared/bus/lease.py) -> the identities that may hold leases of that role, each under its own
# `gd2p/lease/<role>/<identity>/*` only (the first is the role's default, lease.LEASE_IDENTITIES).
LEASE_HOLDERS: dict[str, tuple[str, ...]] = {"planner": ("planner",), "client": ("cli",)}


# ------------------------------------------------------------------------------------------ the table
def _worker_interfaces(svc: Service) -> tuple[Interface, ...]:
    """The three keys of every worker of `svc`: liveliness token, job queryable, status heartbeat."""
    name, own = svc.name, frozenset({svc.name})
    return (
        Interface(f"{name} liveliness", keys.alive_key(name, WORKER_ID), "liveliness",
                  f"A live {name} worker; the last chunk is its worker id, which names its job key.",
                  own, EVERYONE, payload="none (a token)", used_by=_ALIVE_USED_BY, liveliness=_ALIVE_LIVELINESS,
                  code=("shared/bus/worker.py: Worker.run", "shared/bus/dispatcher.py", "shared/bus/discovery.py"),
                  service=name),
        Interface(f"{name} jobs", keys.job_key(name, WORKER_ID), "queryable",
                  f"The queryable of one {name} worker: its jobs and health queries, answered by it alone.",
                  own, own | svc.callers, exchanges=svc.exchanges, used_by=svc.used_by, liveliness=_JOB_LIVELINESS,
                  qos=f"{_JOB_QOS} {svc.qos}", code=("shared/bus/worker.py: Worker", *svc.code), service=name),
        Interface(f"{name} status heartbeat", keys.status_key(name, WORKER_ID), "publication",
                  f"The WorkerStatus of a {name} worker.", own, EVERYONE, message=WorkerStatus,
                  used_by="The recorder (every publication under `gd2p/**`).", qos=_STATUS_QOS,
                  code=("shared/bus/worker.py: Worker._publish_status",), service=name),
    )


def _lease_interface(role: str, identity: str) -> Interface:
    detail = {"planner": (("The lease of one robot command: the planner declares `<worker_id>.<command_id>` before"
                           " it sends the command and names it in ExecutionCommand.lease_token."),
                          ("The robot bridge (`CommandLease`: a LeaseMonitor from before its first check until"
                           " the motion ends; losing the token stops the robot)."),
                          ("services/planner/service.py: BusServices.execute", "services/robot_bridge/bus_safety.py: CommandLease")),
              "client": (("The lease of one push client: declared for one request and named in"
                          " PushRequest.client_lease."),
                         ("The planner (a LeaseMonitor while it serves the request; losing the token cancels the"
                          " request and stops the robot if it moves)."),
                         ("client/push_client.py: push", "services/planner/service.py: BusServices.watch_client"))}
    summary, used_by, code = detail[role]
    title = f"{role} lease" if len(LEASE_HOLDERS[role]) == 1 else f"{role} lease of {identity}"
    return Interface(title, lease_key(role, "<holder>", identity), "liveliness", summary,
                     frozenset({identity}), EVERYONE, payload="none (a token)", used_by=used_by,
                     liveliness="The token is the lease: held while the holder's session lives; its DELETE (the"
                                " holder undeclared it, closed its session or died) reaches the watcher at once.",
                     qos=f"The key names its holder's identity (`{identity}`): only that identity may declare a token"
                         " under it, so one identity cannot hold another's lease. A random part in `<holder>` makes"
                         " each lease key unique (Zenoh merges two tokens on one key). The watcher confirms it once"
                         " with a liveliness query, then follows its subscriber.",
                     code=("shared/bus/lease.py", *code))


_ROBOT = (
    Interface("robot command", keys.ROBOT_COMMAND_KEY, "queryable",
              "Execute a plan on the robot. The reply is the final ExecutionState: status \"done\", \"stopped\""
              " (e-stop or lost lease) or \"refused\" (naming the broken limit, joint and time).",
              frozenset({"robot_bridge"}), frozenset({"planner"}),
              exchanges=(Exchange(ExecutionCommand, (ExecutionState, ErrorReply)),),
              used_by="The planner, for the chosen plan of each push; the bridge runs each command on a thread"
                      " of its own (a second command meanwhile is refused: busy).",
              liveliness="The command's `lease_token` must be a planner lease `gd2p/lease/planner/<holder>` held by"
                         " a live token, watched until the motion ends.",
              qos="One key for the one bridge (not per worker). The planner queries with default consolidation and"
                  " a 300 s timeout, without attachment.",
              code=("services/robot_bridge/service.py: Bridge.serve_commands",
                    "services/planner/service.py: BusServices.execute")),
    Interface("robot state", keys.ROBOT_STATE_KEY, "publication",
              "The robot's joint state, the plan time and the object's tracked pose with the execution status,"
              " streamed while a plan runs.",
              frozenset({"robot_bridge"}), EVERYONE, message=ExecutionState,
              used_by="The planner (the states of its command, by command_id: the push recording, and the"
                      " closed-loop monitor, which compares their object poses with the rollout's); the recorder.",
              qos=f"Published at the robot's state rate while a command executes. {_RECORDED_QOS} The bridge sends"
                  " them from a queue of 1,000 states (2 s at 500 Hz) so its control loop never waits on the bus; a"
                  " state that finds the queue full is dropped with its number, so the recorder counts it missing.",
              code=("services/robot_bridge/service.py: run", "services/planner/service.py: BusServices._on_state",
                    "shared/bus/recorded.py: RecordedPublisher")),
    Interface("object track", keys.OBJECT_TRACK_KEY, "publication",
              "The pushed object's pose as a tracker sees it while a plan runs (stamp, pose, and — when the"
              " publisher knows them — the command and its plan time).",
              frozenset({"robot_bridge", "tracker"}), EVERYONE, message=ObjectTrack,
              used_by="The simulated robot bridge publishes its tracker's frames (20 Hz, noisy and one frame late:"
                      " shared/execution/robots/sim/tracker.py). With hardware a user's tracker publishes here"
                      " and the bridge folds the latest pose into its ExecutionStates (with their plan time), where"
                      " the planner's closed-loop monitor reads it (examples/object_tracker.py publishes one from"
                      " zenoh and msgpack alone); the recorder records both. The pose is of the frame O the"
                      " request gave the planner: the library object's, or for a point-cloud request its"
                      " reconstruction's (centre of mass and principal axes of what was seen, where the cloud"
                      " showed it), which may differ from the library object's own by a half turn.",
              qos="Publish at the tracker's rate (10-30 Hz) while the robot moves; a pose older than 0.5 s is not"
                  f" folded into a state. {_RECORDED_QOS} The simulated bridge sends its frames from a queue like"
                  " its states; examples/object_tracker.py numbers its own.",
              code=("shared/execution/robots/sim/robot.py: SimRobot._track_frame",
                    "services/robot_bridge/service.py: TrackSubscriber")),
    Interface("push decision", keys.PLANNER_DECISION_KEY, "publication",
              "What the planner considered and chose for one push — the candidate hand poses (world) with the"
              " critic's scores, the rolled-out plans with their predicted object paths, the chosen plan — sent"
              " just before that plan goes to the robot bridge.",
              frozenset({"planner"}), EVERYONE, message=PushDecision,
              used_by="The live view (`gd2p view`, `gd2p up --view`: cli/view.py, visualisation/live.py) draws it;"
                      " the recorder records it. The planner also writes it into the push's own MCAP, which"
                      " `gd2p replay FILE --view` plays.",
              qos=f"One per push (corrections and multi-step pushes included), some 50-200 kB. {_RECORDED_QOS}"
                  " The planner sends them from a queue of 16 so a push never waits on a slow viewer.",
              code=("shared/planning/decision_tap.py: DecisionTap", "services/planner/service.py: BusServices.publish_decision",
                    "cli/view.py: ViewBus")),
    Interface("e-stop", keys.ROBOT_ESTOP_KEY, "publication",
              "Stop every robot at once. Anything published here stops the robot — a valid EStop, an empty"
              " payload, garbage — and latches: later commands are refused until the bridge restarts.",
              EVERYONE, EVERYONE, message=EStop,
              used_by="`gd2p bridge estop` publishes; the robot bridge's EStopSubscriber subscribes.",
              qos="Open to every identity on purpose: stopping must never need the planner. A plain put with its own"
                  " settings (not a numbered, blocking publisher: nothing may hold a stop back); the recorder counts"
                  " its samples as received, without sequence numbers.",
              code=("services/robot_bridge/bus_safety.py: EStopSubscriber", "cli/bridge.py: _estop")),
    Interface("held plans", keys.ROBOT_HELD_KEY, "publication",
              "With `--confirm`: a plan the bridge holds until an operator confirms it (the plan, its command id,"
              " when it expires), and once more when the hold ends, with `reason` (confirmed by whom, expired,"
              " dropped: lease lost or e-stop).",
              frozenset({"robot_bridge"}), EVERYONE, message=PlanHeld,
              used_by="The live view and `gd2p confirm --list` (client/confirm.py: held_plans) subscribe; the"
                      " recorder records it.",
              qos="Published when a command is held, again every 1 s while it waits (a late subscriber sees it),"
                  " and when the hold ends (reason set). A plain put from a declared publisher.",
              code=("services/robot_bridge/bus_safety.py: ConfirmServer", "shared/execution/confirm.py: ConfirmGate",
                    "client/confirm.py: held_plans")),
    Interface("plan confirm", keys.ROBOT_CONFIRM_KEY, "queryable",
              "With `--confirm`: an operator's go for one held command. The reply says accepted (the plan runs"
              " now) or why not (unknown id, expired, already confirmed, dropped).",
              frozenset({"robot_bridge"}), frozenset({"operator"}),
              exchanges=(Exchange(PlanConfirm, (PlanConfirmReply, ErrorReply)),),
              used_by="`gd2p confirm ID` and the live view's confirm button, both through client/confirm.py: confirm;"
                      " `PlanConfirm.operator` is logged and named in the command's final ExecutionState.",
              liveliness="None: no answer means no bridge runs with --confirm (or the caller is not the operator).",
              qos="Answered at once (never waits for the motion). Only the operator identity may query it under the"
                  " secure profile: another identity's query is dropped by the router (no answer at all).",
              code=("services/robot_bridge/bus_safety.py: ConfirmServer", "client/confirm.py: confirm")),
)
_INFRASTRUCTURE = (
    Interface("caller presence", keys.caller_key("<id>"), "liveliness",
              "A Dispatcher's token, held while it is open; its jobs name it in their query attachment.",
              EVERYONE, EVERYONE, payload="none (a token)",
              used_by="Every worker (shared/bus/worker.py, Callers): when the token is deleted (the caller closed,"
                      " crashed or lost its router) the caller's queued jobs never start and its running jobs stop"
                      " at their next deadline check, answered ErrorReply \"cancelled\".",
              liveliness="Declared by `Dispatcher(...)` (`<id>` = its session id and a random part), undeclared by"
                         " `close()`.",
              qos="Open to every identity: a token only keeps a caller's jobs from being cancelled early; their"
                  " deadline still bounds them.",
              code=("shared/bus/dispatcher.py: Dispatcher", "shared/bus/worker.py: Worker._on_caller")),
    Interface("router watchdog", WATCHDOG_KEY, "publication",
              "Beats the robot bridge sends itself through the router: a beat can only come back through it, so"
              " their silence shows a router that stopped forwarding, however the link looks. Only the bridge's"
              " own beats count: a forged one is ignored, so it cannot hide a frozen router.",
              frozenset({"robot_bridge"}), EVERYONE,
              payload=f"{BEAT_BYTES} bytes, no encoding (struct `{BEAT_FORMAT}`): the beat number, the probe session's zid, an"
                      " HMAC-SHA256 of both under a secret that never leaves the bridge's process",
              used_by="The robot bridge's RouterWatchdog (`<name>` = `robot_bridge-<zid>`): its probe session"
                      " publishes, its main session subscribes and counts a beat only if it carries the probe's"
                      " zid and a valid MAC and is numbered at most the last beat sent (others are ignored and"
                      " counted). The recorder records the beats too.",
              qos="A beat every 20 ms with congestion control DROP; the subscriber keeps the last 64 (ring channel)."
                  " Put by the bridge's identity only in the secure profile.",
              code=("shared/bus/lease.py: RouterWatchdog",)),
    Interface("launcher control", LAUNCHER_CONTROL_KEY, "queryable",
              "Bring a scalable service to exactly N workers; answered once the new workers have registered.",
              frozenset({"launcher"}), frozenset({"operator"}),
              exchanges=(Exchange(ScaleRequest, (ScaleReply, ErrorReply)),),
              used_by="`deploy/scale_validators.py` (`request_scale`) against a running `gd2p up`.",
              liveliness="None: no answer means no launcher (`gd2p up`) is running.",
              qos="Declared complete=True; `request_scale` waits 120 s by default. A count above the launcher's"
                  " maximum is refused with ErrorReply \"bad_request\" naming the limit.",
              code=("deploy/launcher.py: Launcher._serve_control, request_scale",)),
    Interface("recording", keys.ALL_KEYS, "publication",
              "The recorder's subscription: every publication above, written to MCAP with its key and encoding."
              " Nobody publishes on the whole space.",
              frozenset(), EVERYONE, payload="every publication under `gd2p/**`, as published",
              used_by="The recorder (a FIFO channel of 65,536 samples: back-pressure, not drops); `gd2p replay`"
                      " republishes a recording on the keys it was recorded from (numbered, blocking publishers"
                      " of its own); `gd2p recording-info` prints what the recorder counted.",
              qos="Every recorded publication of this code base (states, tracks, heartbeats, replays) comes from a"
                  " RecordedPublisher: congestion control BLOCK and the sequence attachment. Per key and publisher"
                  " the recorder counts samples received, missing (gaps in the numbers) and late (a number at or"
                  " below one already seen); each MCAP file's metadata holds `gd2p.recording` (commit, recorder"
                  " config, seeds: `--run-seeds` or $GD2P_RUN_SEEDS), `gd2p.counts` (the file's samples) and, in"
                  " the run's final file, `gd2p.counts.total`. Samples without the attachment (e-stop, watchdog"
                  " beats, a foreign publisher) are counted as received only.",
              code=("services/recorder/service.py: RecorderService.run", "visualisation/recorder.py: SequenceCounts",
                    "shared/bus/recorded.py", "cli/recording.py")),
)
INTERFACES: tuple[Interface, ...] = (
    *(row for svc in WORKERS for row in _worker_interfaces(svc)),
    *_ROBOT,
    *(_lease_interface(role, identity) for role in LEASE_ROLES for identity in LEASE_HOLDERS[role]),
    *_INFRASTRUCTURE,
)


def interface(key: str, kind: str | None = None) -> Interface:
    """The row (of `kind`, if given) that `key` is an instance of. The recorder's `gd2p/**` row is found
    by that key alone: a key no other row has is unknown (LookupError), not merely recorded."""
    for row in INTERFACES:
        if (kind is None or row.kind == kind) and (row.key == key or ("**" not in row.key and row.includes(key))):
            return row
    raise LookupError(f"no interface of the registry has the key {key!r}")


def calls() -> dict[str, tuple[str, ...]]:
    """Caller identity -> the services whose worker keys it queries (a worker asking itself left out)."""
    called: dict[str, list[str]] = {}
    for svc in WORKERS:
        for caller in sorted(svc.callers - {svc.name}):
            called.setdefault(caller, []).append(svc.name)
    return {caller: tuple(services) for caller, services in called.items()}


def open_token_keys() -> tuple[str, ...]:
    """The key expressions where every identity may declare a liveliness token (a Dispatcher's presence)."""
    return tuple(row.pattern for row in INTERFACES if row.kind == "liveliness" and row.declarers == EVERYONE)


def open_put_keys() -> tuple[str, ...]:
    """The key expressions every identity may publish on (the e-stop)."""
    return tuple(row.pattern for row in INTERFACES if row.kind == "publication" and row.declarers == EVERYONE)


# ------------------------------------------------------------------------------------------ field tables
def array_aliases() -> dict[str, dict[str, typing.Any]]:
    """Name of each NDArray type of shared/contracts/messages.py (PoseBatch, ...) -> its `array_of` constraints
    (shape, dtypes, min_rows, max_rows, finite), read from the validator that enforces them."""
    aliases = {}
    for name, obj in vars(messages).items():
        if typing.get_origin(obj) is typing.Annotated and obj.__origin__ is messages.NDArray:
            check = obj.__metadata__[0].func
            aliases[name] = dict(zip(check.__code__.co_freevars, (c.cell_contents for c in check.__closure__),
                                     strict=True))
    return aliases


def _alias_of(metadata: typing.Iterable[typing.Any]) -> str | None:
    for item in metadata:
        if isinstance(item, AfterValidator):
            for name, obj in vars(messages).items():
                if typing.get_origin(obj) is typing.Annotated and item in obj.__metadata__:
                    return name
    return None


def type_name(tp: typing.Any) -> str:
    """A readable name of a field's type: NDArray aliases by name, Literal values quoted, X | None."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Annotated:
        return _alias_of(tp.__metadata__) or type_name(args[0])
    if origin is Literal:
        return " | ".join(f'"{a}"' for a in args)
    if origin in (typing.Union, types.UnionType):
        return " | ".join(type_name(a) for a in args)
    if origin is not None:
        return f"{getattr(origin, '__name__', str(origin))}[{', '.join(type_name(a) for a in args)}]"
    return "None" if tp is type(None) else getattr(tp, "__name__", str(tp))


def _constraint(item: typing.Any) -> list[str]:
    symbols = {annotated_types.Ge: ("≥", "ge"), annotated_types.Gt: (">", "gt"),
               annotated_types.Le: ("≤", "le"), annotated_types.Lt: ("<", "lt")}
    if type(item) in symbols:
        symbol, attr = symbols[type(item)]
        return [f"{symbol} {getattr(item, attr)}"]
    if isinstance(item, annotated_types.MinLen):
        return [f"length ≥ {item.min_length}"]
    if isinstance(item, annotated_types.MaxLen):
        return [f"length ≤ {item.max_length}"]
    if getattr(item, "allow_inf_nan", True) is False:
        return ["finite"]
    if getattr(item, "pattern", None):
        return [f"matches `{item.pattern}`"]
    if isinstance(item, FieldInfo):
        return [c for inner in item.metadata for c in _constraint(inner)]
    return []


def constraints(info: FieldInfo) -> list[str]:
    """The checks pydantic applies to a field's value (bounds, lengths, pattern, finiteness)."""
    found = [c for item in info.metadata for c in _constraint(item)]
    for arm in typing.get_args(info.annotation) if typing.get_origin(info.annotation) in (typing.Union, types.UnionType) else ():
        if typing.get_origin(arm) is typing.Annotated:
            found += [c for item in arm.__metadata__ for c in _constraint(item)]
    return list(dict.fromkeys(found))


def default_text(info: FieldInfo) -> str:
    """The value a field takes when the map leaves it out ('required' when it may not)."""
    if info.default_factory is not None:
        if info.default_factory is messages.new_id:
            return "a new random id (uuid4 hex)"
        return repr(info.get_default(call_default_factory=True))
    if info.default is PydanticUndefined:
        return "required"
    value = list(info.default) if isinstance(info.default, tuple) else info.default
    return f'"{value}"' if isinstance(value, str) else repr(value)


def nested_models(model: type[BaseModel]) -> list[type[BaseModel]]:
    """The models used by `model`'s fields, depth first (NDArray included), without `model` itself."""
    found: list[type[BaseModel]] = []

    def visit(tp: typing.Any) -> None:
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            if tp not in found and tp is not model:
                found.append(tp)
                for info in tp.model_fields.values():
                    visit(info.annotation)
            return
        for arg in typing.get_args(tp):
            visit(arg)

    for info in model.model_fields.values():
        visit(info.annotation)
    return found


def message_types() -> list[type[BaseModel]]:
    """Every model a client meets: the messages of the registry in order, then the types nested in them."""
    sent = list(dict.fromkeys(m for row in INTERFACES for m in row.messages()))
    nested = [n for m in sent for n in nested_models(m) if n not in sent]
    return sent + list(dict.fromkeys(nested))


def field_type(info: FieldInfo) -> str:
    """The type of a model field as the tables show it (an NDArray field by its alias, e.g. PoseBatch)."""
    return _alias_of(info.metadata) or type_name(info.annotation)


# ------------------------------------------------------------------------------------------ markdown
def _cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _table(header: tuple[str, ...], rows: typing.Iterable[tuple[str, ...]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]


def _who(identities: frozenset[str]) -> str:
    if not identities:
        return "nobody"
    return "everyone" if identities == EVERYONE else ", ".join(sorted(identities))


def _carried(row: Interface) -> str:
    if row.exchanges:
        return "; ".join(f"{e.request.__name__} → {' or '.join(r.__name__ for r in e.replies)}" for e in row.exchanges)
    return row.message.__name__ if row.message else row.payload


def _anchor(title: str) -> str:
    return re.sub(r"[^a-z0-9 _-]", "", title.lower()).replace(" ", "-")


def _overview() -> list[str]:
    rows = [(f"[`{r.key}`](#{_anchor(r.service or r.title)})", r.kind, _carried(r), _who(r.declarers),
             _who(r.callers)) for r in INTERFACES]
    return ["## Key expressions", "",
            ("`<name>` marks a chunk that varies; a caller matching every instance writes `*` there. "
             "\"Declared by\" serves the queryable, publishes or holds the token; \"called by\" queries, "
             "subscribes or watches the token. These are what the secure profile (`gd2p up --secure`, "
             "deploy/secure/profile.py) allows each identity; without it the router lets anyone do anything."), "",
            *_table(("key expression", "kind", "messages", "declared by", "called by"), rows), ""]


def _participants() -> list[str]:
    return ["## Participants", "",
            ("Each participant joins the router with a session of its own; under the secure profile each has a "
             "certificate whose common name is the identity below."), "",
            *_table(("identity", "what it is"), PARTICIPANTS.items()), ""]


def _section(row: Interface) -> list[str]:
    facts = [("key", f"`{row.key}`"), ("kind", row.kind), ("declared by", _who(row.declarers)),
             ("called by", _who(row.callers)), ("used by", row.used_by)]
    if row.exchanges:
        facts += [("queries", f"{e.request.__name__} → {' or '.join(r.__name__ for r in e.replies)}")
                  for e in row.exchanges]
    elif row.message:
        facts.append(("message", row.message.__name__))
    if row.payload:
        facts.append(("payload", row.payload))
    facts += [(name, text) for name, text in (("liveliness", row.liveliness), ("QoS", row.qos)) if text]
    return [f"### {row.title}", "", row.summary, "", *_table(("", ""), facts), "",
            "Related code:", "", *[f"* {c}" for c in row.code], ""]


def _key_rows(rows: typing.Iterable[Interface]) -> list[str]:
    return _table(("key expression", "kind", "messages", "declared by", "called by"),
                  ((f"`{r.key}`", r.kind, _carried(r), _who(r.declarers), _who(r.callers)) for r in rows))


_WORKER_FAILURES = (
    ("payload over its type's size limit", "ErrorReply \"bad_request\" (size and limit), not even copied"),
    ("payload that does not decode", "ErrorReply \"bad_request\" naming the problem"),
    ("a message type the service does not accept", "ErrorReply \"bad_request\": \"<service> accepts X, Y; got Z\""),
    ("a known job id with a different payload", "ErrorReply \"bad_request\""),
    ("the handler refuses (ServiceError)", "ErrorReply with its code, e.g. \"infeasible\", \"not_implemented\""),
    ("the handler fails otherwise", "ErrorReply \"internal\"; the worker keeps serving"),
    ("the job's budget runs out", "ErrorReply \"timeout\""),
    ("the worker is stopping", "ErrorReply \"unavailable\""),
)


def _workers_intro() -> list[str]:
    generic = [Interface("", keys.alive_key("<service>", WORKER_ID), "liveliness", "", frozenset(), frozenset(),
                         payload="none (a token)"),
               Interface("", keys.job_key("<service>", WORKER_ID), "queryable", "", frozenset(), frozenset(),
                         exchanges=(Exchange(HealthQuery, (WorkerStatus, ErrorReply)),)),
               Interface("", keys.status_key("<service>", WORKER_ID), "publication", "", frozenset(), frozenset(),
                         message=WorkerStatus)]
    rows = [(f"`{r.key}`", r.kind, _carried(r)) for r in generic]
    return ["## Workers", "",
            ("Every service runs its workers on the worker runtime (shared/bus/worker.py), so every worker has the "
             "same three keys; the sections below give each service's jobs and callers."), "",
            *_table(("key expression", "kind", "messages"), rows), "",
            f"* Liveliness token: {_ALIVE_LIVELINESS} Used by: {_ALIVE_USED_BY}",
            f"* Job queryable: {_JOB_LIVELINESS} {_JOB_QOS}",
            f"* Status heartbeat: {_STATUS_QOS} Used by the recorder.", "",
            "A job key answers every query with exactly one reply: the result, or an ErrorReply when", "",
            *_table(("the query brings", "the reply is"), _WORKER_FAILURES), ""]


def _worker_section(svc: Service) -> list[str]:
    size = ("Scalable: `gd2p up` starts one (validators: one per core) and the launcher's control key scales it."
            if svc.scalable else "A singleton: `gd2p up` runs one and does not scale it.")
    rows = [r for r in INTERFACES if r.service == svc.name]
    return [f"### {svc.name}", "", f"{svc.summary[0].upper()}{svc.summary[1:]}. {size}", "", *_key_rows(rows), "",
            f"Used by: {svc.used_by}", "", f"QoS: {svc.qos}", "",
            "Related code:", "", *[f"* {c}" for c in svc.code], ""]


def _keys_of(model: type[Message]) -> list[str]:
    """The keys `model` travels on; a worker key shared by several services with `<service>` in it."""
    rows = [r for r in INTERFACES if model in r.messages()]
    shared = len({r.service for r in rows if r.service}) > 1
    generic = [r.key.replace(f"/{r.service}/", "/<service>/", 1) if shared and r.service else r.key for r in rows]
    return list(dict.fromkeys(generic))


def _linked(type_text: str) -> str:
    """`type_text` with each model name linked to its section and each array type to the array table."""
    targets = {m.__name__: f"#{m.__name__.lower()}" for m in message_types()}
    targets |= {name: "#array-types" for name in array_aliases()}
    return re.sub(r"\b[A-Z]\w*\b", lambda m: f"[{m[0]}]({targets[m[0]]})" if m[0] in targets else m[0], type_text)


def _model_section(model: type[BaseModel]) -> list[str]:
    doc = (inspect.getdoc(model) or "").split("\n\n")[0].replace("\n", " ")
    lines = [f"### {model.__name__}", "", doc, ""]
    if issubclass(model, Message):
        on = _keys_of(model)
        if on:
            lines += [(f"Encoding `{ENCODING_PREFIX}{model.__name__}`; at most {model.MAX_PAYLOAD_BYTES // 2**20} MiB; "
                       f"on {', '.join(f'`{k}`' for k in on)}."), ""]
        else:
            lines += ["Sent nested in other messages only (as a map with its `schema_version` and `id`).", ""]
    rows = [(f"`{name}`", _linked(field_type(info)), default_text(info), ", ".join(constraints(info)))
            for name, info in model.model_fields.items()]
    return lines + _table(("field", "type", "default", "constraints"), rows) + [""]


def _arrays() -> list[str]:
    def shape(spec: dict[str, typing.Any]) -> str:
        names = iter("NMKT")
        return "[" + ", ".join(str(d) if d is not None else next(names) for d in spec["shape"]) + "]"

    rows = [(name, " or ".join(spec["dtypes"]), shape(spec),
             ", ".join(filter(None, (f"at least {spec['min_rows']} row{'s' * (spec['min_rows'] > 1)}"
                                     if spec["min_rows"] else "",
                                     f"at most {spec['max_rows']} rows" if spec["max_rows"] else "",
                                     "finite values" if spec["finite"] and set(spec["dtypes"]) & set(messages.FLOAT_DTYPES)
                                     else ""))))
            for name, spec in array_aliases().items()]
    return ["## Array types", "",
            "Every array field is an [NDArray](#ndarray) map; its type name says which dtypes and shape it accepts.",
            "", *_table(("type", "dtype", "shape", "also"), rows), ""]


# An example PushRequest map as a client builds it (docs/interfaces.md; tests decode it with the codec).
EXAMPLE_PUSH_REQUEST: dict[str, typing.Any] = {
    "schema_version": SCHEMA_VERSION,
    "id": "5c2d0f3e8a9b4c1d9e7f6a5b4c3d2e1f",
    "object": {"library_id": "proc-box-013"},
    "direction_deg": 90.0,
    "method": "fixed",
}

_INTRODUCTION = f"""# Interfaces

<!-- Generated from shared/bus/interfaces.py by `{GENERATED_BY}`:
edit the registry, not this file (tests/test_interfaces.py compares the two). -->

## Introduction

GD2P's services exchange pydantic messages (shared/contracts/messages.py) over one Zenoh router. This document
lists every key expression of the bus: which messages travel on it, who declares it and who calls it,
which liveliness it relies on, its QoS, and how to build its messages without the project's code.
It is generated from the interface registry, shared/bus/interfaces.py, from which the secure
profile's access rules (deploy/secure/profile.py) are built and against which they are tested.
From Python, `shared.bus` does all of this (`Worker`, `Dispatcher`, `client.push_client.push`);
examples/raw_zenoh_push.py does it with zenoh and msgpack alone, following this document.

## Brief overview

* Every process is a Zenoh client of one router (`gd2p up` runs it on tcp/127.0.0.1:7447; the secure
  profile adds mutual TLS and per-identity access control).
* A worker of a service holds a liveliness token, serves a queryable of its own and publishes a status
  heartbeat. Callers choose a worker and query its key (see Discovery and dispatch).
* Requests are queries and answers are their replies; streams (robot state, heartbeats) and the
  e-stop are publications.
* Only the planner commands the robot, under a lease (a liveliness token) whose loss stops the motion.
* The recorder writes every publication under `gd2p/**` to MCAP. Recorded publishers block rather than drop
  and number their samples, so each file's metadata says what was received and what is missing.
"""


def _indented(text: str, spaces: int) -> str:
    return "\n".join(" " * spaces + line for line in text.splitlines())


def _serialization() -> list[str]:
    codes = ", ".join(f'"{c}"' for c in ErrorReply.CODES)
    return ["## Serialization", "", f"""A payload is the [msgpack](https://msgpack.org) encoding of one message: a map from field names
to values. The Zenoh encoding names the message type: `{ENCODING_PREFIX}<Model>`, e.g.
`{ENCODING_PREFIX}PushRequest`. A receiver takes the model from the encoding (a worker's key needs
it; the robot command and launcher control keys assume their request type without one); a payload of
an unknown or unexpected model, or whose map does not validate, is answered with ErrorReply
"bad_request" naming the problem.

* Every message map has `schema_version` (this build speaks {SCHEMA_VERSION} and refuses any other) and `id`
  (1-128 characters). On a worker's key the id names the job: the same id with the same payload is the
  same job, computed once; the same id with another payload is refused.
* Fields are those of the [message tables](#messages). A field left out takes its default; a
  "required" one must be there; a key the model does not have is refused.
* None is msgpack nil, `bytes` fields are msgpack bin (not str), tuples and lists are arrays, nested
  models are maps (value types carry no `schema_version` or `id`).
* An array is an [NDArray](#ndarray) map `{{"dtype": "float64", "shape": [25], "data": <bin>}}`: `data`
  holds the elements in C (row-major) order, little-endian, exactly prod(shape) × itemsize bytes. With
  numpy: `np.frombuffer(data, dtype="<f8").reshape(shape)`, and back
  `{{"dtype": "float64", "shape": list(a.shape), "data": a.astype("<f8").tobytes()}}`.
* A payload larger than its type's limit (below) is refused before it is decoded.
* A reply is a message too, its encoding naming its model: the result, or an ErrorReply whose `code`
  is one of {codes}.
""", "### Calling a worker without the project's code", "", f"""What examples/raw_zenoh_push.py does, with zenoh and msgpack only:

1. Find a worker: a liveliness query on `{keys.alive_pattern('planner')}`; each reply's key ends with a
   worker id.
2. Build the message map, e.g. a PushRequest for the library object proc-box-013 pushed towards 90°
   with the fixed spatula pose (every other field takes its default):

   ```python
{_indented(json.dumps(EXAMPLE_PUSH_REQUEST, indent=4), 3)}
   ```

3. Query that worker's key, `{keys.job_key('planner', WORKER_ID)}`, with the payload
   `msgpack.packb(request, use_bin_type=True)`, the encoding `{ENCODING_PREFIX}PushRequest`,
   consolidation NONE, a timeout T and the attachment `msgpack.packb({{"timeout_s": T}})`.
4. Decode the reply: `msgpack.unpackb(payload, raw=False)` into the model its encoding names. A
   PushResponse has `success` and `result.final_object_pose.position` ([x, y, z], metres); an
   ErrorReply has `code` and `message`.
"""]


_DISPATCH = f"""## Discovery and dispatch

Zenoh has no work queue: the caller chooses the worker. Each worker holds a liveliness token
`{keys.alive_key('<service>', WORKER_ID)}` and serves a queryable of its own,
`{keys.job_key('<service>', WORKER_ID)}`. A dispatcher (shared/bus/dispatcher.py)

* learns the live workers from a liveliness subscriber on `{keys.alive_pattern('<service>')}` with
  history=True; a worker is gone when the DELETE of its token arrives;
* sends each job to the live worker with the fewest jobs in flight, skipping workers at their
  `max_in_flight_per_worker`, shutting down (they answered "unavailable") or cooling down (their last
  query ended without a reply: skipped for 1 s); among equals it prefers a worker that has not failed
  this job yet, then the one sent the fewest jobs;
* queries that worker's key alone, with consolidation NONE and the attachment `{{"timeout_s": T}}`;
* takes every reply as final, ErrorReply included, except "unavailable" (sent to another worker
  without counting as an attempt); a job whose worker's token disappears, whose query ends without a
  reply or that gets none within T is sent again, preferably elsewhere, up to `max_attempts` times.

A worker gives each job a budget: its own deadline (1 h by default), shortened to just under the
caller's `timeout_s` when the attachment says it; past it the answer is ErrorReply "timeout". Replies
are cached by job id with the SHA-256 of the payload, so a job sent twice is computed once.
"""


def markdown() -> str:
    """docs/interfaces.md: the registry, its messages and their fields, and how to use them."""
    lines = [_INTRODUCTION, *_participants(), *_overview(), *_serialization(), _DISPATCH, *_workers_intro()]
    lines += [line for svc in WORKERS for line in _worker_section(svc)]
    lines += ["## Robot, leases and infrastructure", ""]
    lines += [line for row in INTERFACES if row.service is None for line in _section(row)]
    lines += ["## Messages", "", "Every message, then the value types nested in them. Generated from the pydantic models.", ""]
    lines += [line for model in message_types() for line in _model_section(model)]
    lines += _arrays()
    return "\n".join(lines).rstrip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m shared.bus.interfaces", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--markdown", action="store_true", help="print docs/interfaces.md")
    args = parser.parse_args(argv)
    if not args.markdown:
        parser.print_help()
        return 2
    sys.stdout.write(markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Zenoh configs of the secure deployment profile: mutual TLS plus per-identity access control.

The router accepts only TLS links whose client presents a certificate signed by the deployment CA
(`enable_mtls`); the certificate's common name (CN) is the session's identity. Its access-control
rules are default-deny, and each key space has an owner:

- `gd2p/alive/S/**`, `gd2p/status/S/**`, `gd2p/S/**` (its worker keys `gd2p/S/worker/**` included):
  only identity S declares liveliness tokens, publishes, declares queryables and replies there, and
  only S is handed the queries sent there. S is one of SERVING_IDENTITIES (the six services and the
  launcher). So the robot state (`gd2p/robot_bridge/state`) and the command replies come from the
  bridge only, and nobody but a planner can announce itself as a planner, answer a push or publish the
  live view's push decisions (`gd2p/planner/decision`).
- worker keys are queried only by the callers that really call S (CALLS: the planner calls the sampler
  and validators; the operator's tools, CN "cli", call the planner, generator, validator and sampler
  and health-query everyone) and by S itself (its container healthcheck asks its own worker).
- `gd2p/robot_bridge/command/**`: only the planner queries (or puts); the bridge serves it.
- `gd2p/lease/<role>/<identity>/*` (shared/bus/lease.py): only that identity declares the token, and only
  for a role it may hold (LEASE_HOLDERS: role "planner" -> CN planner, role "client" -> CN cli; one rule
  per identity and role, as Zenoh's key expressions cannot say "the session's own CN"). So a lease key
  names its holder's identity, and one identity cannot hold another's lease.
- `gd2p/launcher/**`: only CN "operator" queries it (scaling is host administration, kept apart from
  the "cli" certificate that every push/dataset client carries); the launcher identity serves it.
- `gd2p/robot_bridge/object_track`: besides the bridge (its namespace), CN "tracker" may put: a user's
  object tracker beside real hardware.
- `gd2p/robot_bridge/confirm` (`gd2p up --confirm`): only CN "operator" queries it (CONFIRMERS: releasing
  a held plan moves the robot; the "cli" certificate of every push client may not); the bridge serves it
  and publishes the held plans on `gd2p/robot_bridge/held` (its namespace; every identity may subscribe).
- `gd2p/robot_bridge/estop`: every authenticated identity may put (stopping must never need the planner).
- `gd2p/watchdog/*` (router watchdog beats, shared/bus/lease.py RouterWatchdog): only CN robot_bridge puts
  (WATCHDOG_BEATERS: the bridge's probe session beats to its main session). A beat from anyone else is
  ignored by the watchdog anyway (it carries the probe's zid and a MAC only the bridge can make), and the
  router drops it before it reaches the bridge: it can neither hide a frozen router nor flood the ring.
- every identity may subscribe, liveliness-subscribe and liveliness-query `gd2p/**` (observers: the
  recorder, `gd2p status`, a dispatcher watching workers, the bridge watching a lease); the router
  tells every session which subscribers, queryables and tokens exist and delivers every publication.

`allowed(identity, flow, message, key)` evaluates the same rules the way Zenoh does (a rule applies
when one of its key expressions includes the message's), for tests and for docs/safety.md.
A key outside every rule is dropped for everyone: a new key (shared/bus/keys.py) needs an owner here.
The tables (WORKER_IDENTITIES, CALLS, LEASE_HOLDERS, OPEN_PUT_KEYS, WATCHDOG_BEATERS, CONFIRMERS) come from the interface registry,
shared/bus/interfaces.py; tests/test_interfaces.py checks every registry entry against these rules.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import zenoh

from deploy.secure.certs import IDENTITIES, ROUTER_IDENTITY, credentials
from shared.bus import interfaces
from shared.bus.keys import (
    ALIVE_PREFIX,
    ALL_KEYS,
    LEASE_PREFIX,
    OBJECT_TRACK_KEY,
    PREFIX,
    ROBOT_COMMAND_KEY,
    ROBOT_CONFIRM_KEY,
    STATUS_PREFIX,
)

COMMAND_KEYS = f"{ROBOT_COMMAND_KEY.rsplit('/', 1)[0]}/**"  # gd2p/robot_bridge/command/**
COMMANDER_IDENTITY = "planner"
BRIDGE_IDENTITY = "robot_bridge"
OPERATOR_IDENTITY = "operator"
TRACKER_IDENTITY = "tracker"
LAUNCHER_IDENTITY = "launcher"
LAUNCHER_KEYS = f"{PREFIX}/{LAUNCHER_IDENTITY}/**"  # the launcher's control key gd2p/launcher/control
# Processes that run workers: a liveliness token, a status heartbeat and a worker queryable each.
WORKER_IDENTITIES: tuple[str, ...] = interfaces.SERVICES
# Identities that own a namespace gd2p/<S>/** (plus gd2p/alive/<S>/** and gd2p/status/<S>/**).
SERVING_IDENTITIES: tuple[str, ...] = (*WORKER_IDENTITIES, LAUNCHER_IDENTITY)
# Who sends jobs or health queries to whose worker keys (besides each worker asking itself):
# services/planner/service.py dispatches to sampler and validator; the operator's tools (gd2p push,
# dataset build, health) reach the planner, generator and validator, and `gd2p health` every service.
CALLS: dict[str, tuple[str, ...]] = interfaces.calls()
# Lease role (gd2p/lease/<role>/<identity>/<holder>, shared/bus/lease.py) -> the identities that may hold it.
LEASE_HOLDERS: dict[str, tuple[str, ...]] = dict(interfaces.LEASE_HOLDERS)
# Keys every authenticated identity may put on: the e-stop (stopping must never need the planner).
OPEN_PUT_KEYS: tuple[str, ...] = interfaces.open_put_keys()  # gd2p/robot_bridge/estop
# The router watchdogs' beats (shared/bus/lease.py RouterWatchdog): the bridge's probe session beats on
# gd2p/watchdog/<name> to its main session. A forged beat could hide a frozen router, so only the
# identities of the registry row put there (robot_bridge).
_WATCHDOG = interfaces.interface(interfaces.WATCHDOG_KEY, "publication")
WATCHDOG_KEYS = _WATCHDOG.pattern  # gd2p/watchdog/*
WATCHDOG_BEATERS: tuple[str, ...] = tuple(sorted(_WATCHDOG.declarers))  # robot_bridge
# Preview and confirm (`gd2p up --confirm`): the identities that may confirm a held plan (operator).
_CONFIRM = interfaces.interface(ROBOT_CONFIRM_KEY, "queryable")
CONFIRM_KEY = _CONFIRM.pattern  # gd2p/robot_bridge/confirm
CONFIRMERS: tuple[str, ...] = tuple(sorted(_CONFIRM.callers))  # operator
# Tokens every identity may declare: a Dispatcher's presence (gd2p/caller/*), whose only power is to keep
# its own jobs from being cancelled before their deadline.
OPEN_TOKEN_KEYS: tuple[str, ...] = interfaces.open_token_keys()

MESSAGES: tuple[str, ...] = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                             "liveliness_token", "liveliness_query", "declare_liveliness_subscriber")
FLOWS: tuple[str, ...] = ("ingress", "egress")
EVERYONE = "authenticated"  # the subject without a CN constraint: mTLS is mandatory, so every linked session


def _rule(rule_id: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": key_exprs}


def _worker_keys(service: str) -> str:
    return f"{PREFIX}/{service}/worker/**"


def _rules_by_subject() -> dict[str, list[dict[str, Any]]]:
    """subject (EVERYONE or an identity) -> the allow rules it gets."""
    by_subject: dict[str, list[dict[str, Any]]] = {EVERYONE: [
        # Observers: subscriptions and liveliness look-ups anywhere; the router may tell everyone what
        # exists (declarations, tokens) and deliver every publication. None of it lets a session put,
        # serve, query or reply anywhere: those are the owners' rules below.
        _rule("observe", "ingress", ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
              [ALL_KEYS]),
        _rule("discover", "egress", ["put", "delete", "declare_subscriber", "declare_queryable", "liveliness_token",
                                     "declare_liveliness_subscriber", "liveliness_query"], [ALL_KEYS]),
        _rule("open-puts", "ingress", ["put"], list(OPEN_PUT_KEYS)),
        _rule("open-tokens", "ingress", ["liveliness_token"], list(OPEN_TOKEN_KEYS)),
    ]}
    for identity in IDENTITIES:
        by_subject[identity] = []
    for s in SERVING_IDENTITIES:
        by_subject[s] += [
            _rule(f"{s}-token", "ingress", ["liveliness_token"], [f"{ALIVE_PREFIX}/{s}/**"]),
            _rule(f"{s}-status", "ingress", ["put", "delete"], [f"{STATUS_PREFIX}/{s}/**"]),
            _rule(f"{s}-serve", "ingress", ["put", "delete", "declare_queryable", "reply"], [f"{PREFIX}/{s}/**"]),
            _rule(f"{s}-receive-queries", "egress", ["query"], [f"{PREFIX}/{s}/**"]),
        ]
    for caller in IDENTITIES:
        callees = [*CALLS.get(caller, ()), *((caller,) if caller in WORKER_IDENTITIES else ())]
        if callees:
            called = [_worker_keys(c) for c in dict.fromkeys(callees)]
            by_subject[caller] += [_rule(f"{caller}-call", "ingress", ["query"], called),
                                   _rule(f"{caller}-hear-replies", "egress", ["reply"], called)]
    by_subject[COMMANDER_IDENTITY] += [
        _rule("command-issue", "ingress", ["query", "put"], [COMMAND_KEYS]),
        _rule("command-hear-replies", "egress", ["reply"], [COMMAND_KEYS]),
    ]
    for role, holders in LEASE_HOLDERS.items():
        for holder in holders:  # its own identity's part only: gd2p/lease/<role>/<holder>/*
            by_subject[holder].append(_rule(f"lease-{role}-{holder}", "ingress", ["liveliness_token"],
                                            [f"{LEASE_PREFIX}/{role}/{holder}/*"]))
    by_subject[OPERATOR_IDENTITY] += [
        _rule("launcher-control", "ingress", ["query"], [LAUNCHER_KEYS]),
        _rule("launcher-hear-replies", "egress", ["reply"], [LAUNCHER_KEYS]),
    ]
    for confirmer in CONFIRMERS:
        by_subject[confirmer] += [
            _rule(f"{confirmer}-confirm", "ingress", ["query"], [CONFIRM_KEY]),
            _rule(f"{confirmer}-confirm-replies", "egress", ["reply"], [CONFIRM_KEY]),
        ]
    by_subject[TRACKER_IDENTITY].append(_rule("object-track", "ingress", ["put"], [OBJECT_TRACK_KEY]))
    for beater in WATCHDOG_BEATERS:
        by_subject[beater].append(_rule(f"{beater}-watchdog-beats", "ingress", ["put"], [WATCHDOG_KEYS]))
    return by_subject


def access_control() -> dict[str, Any]:
    """The router's `access_control` section (default deny; see the module docstring)."""
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for subject, subject_rules in _rules_by_subject().items():
        if not subject_rules:
            continue
        rules += subject_rules
        subjects.append({"id": subject} if subject == EVERYONE else {"id": subject, "cert_common_names": [subject]})
        policies.append({"id": f"{subject}-may", "rules": [r["id"] for r in subject_rules], "subjects": [subject]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def allowed(identity: str, flow: str, message: str, key_expr: str) -> bool:
    """Would the router let `identity`'s session do `message` on `key_expr` (its `flow`: "ingress" is
    what the session sends, "egress" what the router hands it)? Zenoh's rule: some allow rule of a
    subject matching the session has that flow and message and a key expression *including* `key_expr`."""
    if flow not in FLOWS or message not in MESSAGES:
        raise ValueError(f"unknown flow {flow!r} or message {message!r}")
    if identity not in IDENTITIES:
        raise ValueError(f"unknown identity {identity!r}; identities: {', '.join(IDENTITIES)}")
    key = zenoh.KeyExpr(key_expr)
    by_subject = _rules_by_subject()
    return any(flow in rule["flows"] and message in rule["messages"]
               and any(zenoh.KeyExpr(k).includes(key) for k in rule["key_exprs"])
               for subject in (EVERYONE, identity) for rule in by_subject[subject])


def who_may(flow: str, message: str, key_expr: str) -> frozenset[str]:
    """The identities that `allowed` lets do `message` on `key_expr`."""
    return frozenset(i for i in IDENTITIES if allowed(i, flow, message, key_expr))


def _tls(cert_dir: Path, identity: str, listen: bool, mounted_at: str | None) -> dict[str, Any]:
    creds = credentials(cert_dir, identity)

    def where(path: Path) -> str:  # the path the reading process sees (e.g. a container's mount point)
        return f"{mounted_at.rstrip('/')}/{path.name}" if mounted_at else str(path)

    tls: dict[str, Any] = {"root_ca_certificate": where(creds.ca_certificate), "enable_mtls": True,
                           "verify_name_on_connect": True}
    side = "listen" if listen else "connect"
    tls[f"{side}_certificate"] = where(creds.certificate)
    tls[f"{side}_private_key"] = where(creds.private_key)
    return tls


def router_config(cert_dir: str | Path, listen: list[str], mounted_at: str | None = None) -> dict[str, Any]:
    """Router: TLS-only listeners with mandatory client certificates, and the access-control rules."""
    if not listen or any(not e.startswith("tls/") for e in listen):
        raise ValueError(f"a secure router listens on tls/ endpoints only, got {listen}")
    return {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"tls": _tls(Path(cert_dir), ROUTER_IDENTITY, True, mounted_at)}},
        "access_control": access_control(),
    }


def client_config(cert_dir: str | Path, identity: str, connect: list[str], mounted_at: str | None = None) -> dict[str, Any]:
    """A client of the secure router, authenticating as `identity`. `mounted_at`: where the reading
    process sees `cert_dir` (a container's volume), if not at the same path."""
    if not connect or any(not e.startswith("tls/") for e in connect):
        raise ValueError(f"a secure client connects to tls/ endpoints only, got {connect}")
    return {
        "mode": "client",
        "connect": {"endpoints": list(connect), "timeout_ms": -1},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"tls": _tls(Path(cert_dir), identity, False, mounted_at)}},
    }


def write_json5(config: dict[str, Any], path: str | Path) -> Path:
    """Write a config (JSON is valid json5) that `zenoh.Config.from_file` / `--zenoh-config` read."""
    path = Path(path)
    path.write_text("// Generated by deploy.secure; regenerate rather than edit.\n" + json.dumps(config, indent=2) + "\n")
    return path

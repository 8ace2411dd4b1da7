"""Zenoh configs of the secure deployment profile: mutual TLS plus access control.

Who may command the robot: the router accepts only TLS links whose client presents a certificate
signed by the deployment CA (`enable_mtls`), and its access-control rules (default: deny) let
- every authenticated identity use the ordinary bus keys (liveliness, status, worker jobs and health,
  the launcher's control key, leases, each service's namespace, the bridge's state and e-stop keys)
  and subscribe to `gd2p/**`;
- only the planner's identity (certificate CN "planner") put or query `gd2p/robot_bridge/command/**`;
- only the robot bridge's identity serve those keys (declare a queryable/subscriber, receive the
  queries and puts, answer them).
A session without a client certificate cannot open a link at all; a certificate with another CN
gets its command dropped at the router, so it never reaches the bridge.

The e-stop key stays open to every identity on purpose: stopping must never need the planner.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from deploy.secure.certs import ROUTER_IDENTITY, credentials

COMMAND_KEYS = "gd2p/robot_bridge/command/**"
COMMANDER_IDENTITY = "planner"
BRIDGE_IDENTITY = "robot_bridge"
# Keys every authenticated identity may use for every kind of message: the shared keys (liveliness,
# status, leases, the launcher), each service's own namespace, and the bridge's worker/state/e-stop keys
# (its worker key serves health queries; it executes commands only on COMMAND_KEYS). The default is
# deny, so a key outside these (a new service's namespace) must be added here.
BUS_KEYS: tuple[str, ...] = (
    "gd2p/alive/**", "gd2p/status/**", "gd2p/lease/**", "gd2p/launcher/**", "gd2p/*/worker/**",
    "gd2p/generator/**", "gd2p/validator/**", "gd2p/sampler/**", "gd2p/planner/**", "gd2p/recorder/**",
    "gd2p/robot_bridge/state/**", "gd2p/robot_bridge/estop",
)
_ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                 "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"]


def access_control() -> dict[str, Any]:
    """The router's `access_control` section (default deny; see the module docstring)."""
    rules = [
        {"id": "bus", "permission": "allow", "flows": ["ingress", "egress"], "messages": _ALL_MESSAGES,
         "key_exprs": list(BUS_KEYS)},
        # Observers (the recorder, `gd2p status`) subscribe to everything; a subscription moves nothing.
        {"id": "observe", "permission": "allow", "flows": ["ingress", "egress"],
         "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
         "key_exprs": ["gd2p/**"]},
        {"id": "command-issue", "permission": "allow", "flows": ["ingress"], "messages": ["put", "query"],
         "key_exprs": [COMMAND_KEYS]},
        {"id": "command-reply-to-planner", "permission": "allow", "flows": ["egress"], "messages": ["reply"],
         "key_exprs": [COMMAND_KEYS]},
        {"id": "command-serve", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_queryable", "declare_subscriber", "reply"], "key_exprs": [COMMAND_KEYS]},
        {"id": "command-deliver-to-bridge", "permission": "allow", "flows": ["egress"], "messages": ["put", "query"],
         "key_exprs": [COMMAND_KEYS]},
    ]
    subjects = [
        {"id": "authenticated"},  # mTLS is mandatory, so every linked session is authenticated
        {"id": "planner", "cert_common_names": [COMMANDER_IDENTITY]},
        {"id": "robot_bridge", "cert_common_names": [BRIDGE_IDENTITY]},
    ]
    policies = [
        {"id": "everyone", "rules": ["bus", "observe"], "subjects": ["authenticated"]},
        {"id": "planner-commands", "rules": ["command-issue", "command-reply-to-planner"], "subjects": ["planner"]},
        {"id": "bridge-serves", "rules": ["command-serve", "command-deliver-to-bridge"], "subjects": ["robot_bridge"]},
    ]
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


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

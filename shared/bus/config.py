"""Zenoh session configuration: one dataclass filled from flags, environment or a config file.

Every process of the system (services, CLIs, tests) opens its session through `open_session`,
so the rules that matter on this bus live here once:
- multicast scouting is always off (deployments name their router explicitly);
- services connect with `connect_timeout_ms=-1` (retry forever), so start order does not matter;
- CLIs pass a finite timeout and get `RouterUnreachable` naming the endpoints instead of a hang.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import threading
from dataclasses import dataclass, replace

import zenoh

from shared.bus.errors import BusError, OpenCancelled, RouterUnreachable

log = logging.getLogger("gd2p.bus")

MODES = ("client", "peer", "router")
DEFAULT_ROUTER_ENDPOINT = "tcp/127.0.0.1:7447"

ENV_MODE = "GD2P_ZENOH_MODE"
ENV_CONNECT = "GD2P_ZENOH_CONNECT"
ENV_LISTEN = "GD2P_ZENOH_LISTEN"
ENV_CONFIG = "GD2P_ZENOH_CONFIG"
# A client that waits "forever" for its router retries in slices this long, so signals get through.
_RETRY_SLICE_MS = 1000


def _split_endpoints(text: str | None) -> list[str] | None:
    """'tcp/a:1, tcp/b:2' -> ['tcp/a:1', 'tcp/b:2']; None or blank -> None (not set)."""
    if text is None:
        return None
    endpoints = [part.strip() for part in text.split(",") if part.strip()]
    return endpoints or None


@dataclass
class BusConfig:
    """How a process joins the bus.

    `connect` / `listen` left as None take the mode's default — unless `config_file` is given, in
    which case the file's endpoints are kept. Explicit values always override the file.
    Defaults: a client connects to `tcp/127.0.0.1:7447`; a router listens there.
    """

    mode: str = "client"
    connect: list[str] | None = None
    listen: list[str] | None = None
    connect_timeout_ms: int = -1
    config_file: str | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise BusError(f"unknown Zenoh mode {self.mode!r}; choose one of {', '.join(MODES)}")
        if self.config_file is None:
            if self.connect is None:
                self.connect = [DEFAULT_ROUTER_ENDPOINT] if self.mode == "client" else []
            if self.listen is None:
                self.listen = [DEFAULT_ROUTER_ENDPOINT] if self.mode == "router" else []
        elif not os.path.isfile(self.config_file):
            raise BusError(f"Zenoh config file {self.config_file!r} does not exist")
        if self.mode == "client" and self.config_file is None and not self.connect:
            raise BusError("a Zenoh client needs at least one endpoint to connect to (e.g. tcp/127.0.0.1:7447)")

    # ----------------------------------------------------------------- constructors
    @classmethod
    def from_env(cls, environ: dict[str, str] | None = None, connect_timeout_ms: int = -1) -> BusConfig:
        """Read GD2P_ZENOH_MODE, GD2P_ZENOH_CONNECT / _LISTEN (comma-separated), GD2P_ZENOH_CONFIG."""
        env = os.environ if environ is None else environ
        return cls(
            mode=env.get(ENV_MODE) or "client",
            connect=_split_endpoints(env.get(ENV_CONNECT)),
            listen=_split_endpoints(env.get(ENV_LISTEN)),
            connect_timeout_ms=connect_timeout_ms,
            config_file=env.get(ENV_CONFIG) or None,
        )

    @staticmethod
    def add_cli_args(parser: argparse.ArgumentParser) -> None:
        """Add --mode, --connect, --listen, --zenoh-config; unset flags fall back to the environment."""
        group = parser.add_argument_group("Zenoh bus")
        group.add_argument("--mode", choices=MODES, default=None, help=f"session mode (env {ENV_MODE}; default client)")
        group.add_argument(
            "--connect", default=None, metavar="ENDPOINTS",
            help=f"comma-separated endpoints to connect to (env {ENV_CONNECT}; default {DEFAULT_ROUTER_ENDPOINT})",
        )
        group.add_argument("--listen", default=None, metavar="ENDPOINTS", help=f"comma-separated endpoints to listen on (env {ENV_LISTEN})")
        group.add_argument("--zenoh-config", default=None, metavar="FILE", help=f"Zenoh json5 config merged first (env {ENV_CONFIG})")

    @classmethod
    def from_args(cls, args: argparse.Namespace, connect_timeout_ms: int = -1) -> BusConfig:
        """Build from `add_cli_args` flags; each unset flag takes its environment variable."""
        env = cls.from_env(connect_timeout_ms=connect_timeout_ms)
        connect = _split_endpoints(getattr(args, "connect", None))
        listen = _split_endpoints(getattr(args, "listen", None))
        return cls(
            mode=getattr(args, "mode", None) or env.mode,
            connect=connect if connect is not None else _split_endpoints(os.environ.get(ENV_CONNECT)),
            listen=listen if listen is not None else _split_endpoints(os.environ.get(ENV_LISTEN)),
            connect_timeout_ms=connect_timeout_ms,
            config_file=getattr(args, "zenoh_config", None) or env.config_file,
        )

    # ----------------------------------------------------------------- conversion
    def to_zenoh(self) -> zenoh.Config:
        """The zenoh.Config: the file (if any) first, then this object's settings on top."""
        try:
            cfg: zenoh.Config = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
            cfg.insert_json5("mode", json.dumps(self.mode))
            if self.connect is not None:
                cfg.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
            if self.listen is not None:
                cfg.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
            cfg.insert_json5("connect/timeout_ms", json.dumps(int(self.connect_timeout_ms)))
            cfg.insert_json5("scouting/multicast/enabled", "false")
        except zenoh.ZError as exc:
            raise BusError(f"invalid Zenoh configuration ({self.describe()}): {_short(exc)}") from None
        return cfg

    def describe(self) -> str:
        """Short human-readable summary for logs and error messages."""
        where = ", ".join(self.connect or []) or "(from config file)"
        return f"{self.mode} -> {where}"


def _short(exc: Exception) -> str:
    """A Zenoh error message without the Rust source locations."""
    return str(exc).split(" at /")[0].rstrip(".")


def open_session(cfg: BusConfig | None = None, stop: threading.Event | None = None) -> zenoh.Session:
    """Open a Zenoh session; close it (or use `with`) when done — an unclosed session can hang exit.

    A client with `connect_timeout_ms=-1` waits for a router indefinitely, but in slices of
    `_RETRY_SLICE_MS` so the wait stays interruptible: Ctrl-C raises KeyboardInterrupt between
    slices, and setting `stop` (e.g. from a SIGTERM handler) raises `OpenCancelled`.
    With a finite timeout, raises `RouterUnreachable` naming the endpoints.
    """
    cfg = cfg or BusConfig.from_env()
    if cfg.mode != "client" or cfg.connect_timeout_ms >= 0:
        return _open_once(cfg)
    attempt = replace(cfg, connect_timeout_ms=_RETRY_SLICE_MS)
    waited_ms = 0
    while True:
        try:
            return _open_once(attempt)
        except RouterUnreachable as exc:
            if waited_ms == 0 or waited_ms % 10_000 < _RETRY_SLICE_MS:
                log.info("%s; still waiting", exc)
        waited_ms += _RETRY_SLICE_MS
        if stop is not None and stop.is_set():
            raise OpenCancelled(f"stopped while waiting for a Zenoh router at {', '.join(cfg.connect or [])}")


def _open_once(cfg: BusConfig) -> zenoh.Session:
    try:
        return zenoh.open(cfg.to_zenoh())
    except zenoh.ZError as exc:
        reason = _short(exc)
        if cfg.mode == "client" and "connect" in reason.lower():
            endpoints = ", ".join(cfg.connect or []) or f"the endpoints of {cfg.config_file}"
            raise RouterUnreachable(
                f"no Zenoh router reachable at {endpoints} (waited {cfg.connect_timeout_ms} ms): {reason}. "
                f"Start one with `gd2p up`, or point {ENV_CONNECT} / --connect at a running router."
            ) from None
        raise BusError(f"cannot open a Zenoh {cfg.mode} session ({cfg.describe()}): {reason}") from None

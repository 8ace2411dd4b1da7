"""`gd2p view [--port PORT]`: the live view of a running system, in the browser.

The bus adapter of `visualisation.live.LiveView`: it subscribes to what the view draws — the planner's
`PushDecision`s (gd2p/planner/decision), the robot's `ExecutionState`s (gd2p/robot_bridge/state), the
tracker's `ObjectTrack`s (gd2p/robot_bridge/object_track) and the bridge's held plans (gd2p/robot_bridge/held,
`gd2p up --confirm`) — and the view's Confirm button queries the bridge through `client.confirm.confirm`.
It only listens: a push from `gd2p push`, from any other client or from the evaluation's own system is
drawn alike, and the view never slows a push (the subscribers hand samples to the view's queue and return).
`gd2p up --view [PORT]` starts it beside the services (deploy/launcher.py).
"""
from __future__ import annotations

import argparse
import getpass
import logging
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from shared.bus.keys import OBJECT_TRACK_KEY, PLANNER_DECISION_KEY, ROBOT_HELD_KEY, ROBOT_STATE_KEY
from shared.contracts.codec import CodecError, decode
from shared.contracts.messages import ExecutionState, ObjectTrack, PlanConfirmReply, PlanHeld, PushDecision
from visualisation.live import DEFAULT_PORT, LiveView

log = logging.getLogger("gd2p.view")


class ViewBus:
    """Feeds `view` from `session`'s subscriptions; `close()` undeclares them (the view stays)."""

    def __init__(self, session: zenoh.Session, view: LiveView):
        self.session = session
        self.view = view
        routes: list[tuple[str, type, Callable[[Any], None]]] = [
            (PLANNER_DECISION_KEY, PushDecision, view.show_decision),
            (ROBOT_STATE_KEY, ExecutionState, view.show_state),
            (OBJECT_TRACK_KEY, ObjectTrack, view.show_track),
            (ROBOT_HELD_KEY, PlanHeld, view.show_held),
        ]
        self._subscribers = [session.declare_subscriber(key, _handler(kind, show)) for key, kind, show in routes]

    def confirm(self, command_id: str) -> PlanConfirmReply:
        """The Confirm button: the contract's client call (client/confirm.py), as the view's operator."""
        from client.confirm import confirm  # type: ignore[import-not-found, unused-ignore]

        reply: PlanConfirmReply = confirm(self.session, command_id, operator=getpass.getuser())
        return reply

    def close(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers = []


def _handler(kind: type, show: Callable[[Any], None]) -> Callable[[zenoh.Sample], None]:
    def on_sample(sample: zenoh.Sample) -> None:  # zenoh callback: decode and queue, never block
        try:
            message = decode(sample.payload.to_bytes(), str(sample.encoding), kind)
        except CodecError as exc:
            log.debug("view: ignoring a sample on %s: %s", sample.key_expr, exc)
            return
        show(message)

    return on_sample


def confirm_available() -> bool:
    try:
        import client.confirm  # type: ignore[import-not-found, unused-ignore]  # noqa: F401
    except ImportError:
        return False
    return True


def serve(cfg: Any, port: int = DEFAULT_PORT, host: str = "127.0.0.1", stop: threading.Event | None = None,
          ready: Callable[[LiveView], None] | None = None) -> None:
    """Serve the live view of the system behind `cfg` (a BusConfig) until `stop` (or Ctrl-C)."""
    from shared.bus import open_session

    stop = stop or threading.Event()
    session = open_session(cfg, stop=stop)
    holder: dict[str, ViewBus] = {}
    on_confirm = (lambda command_id: holder["bus"].confirm(command_id)) if confirm_available() else None
    view = LiveView(port=port, host=host, on_confirm=on_confirm)
    bus = holder["bus"] = ViewBus(session, view)
    try:
        if ready is not None:
            ready(view)
        stop.wait()
    finally:
        bus.close()
        view.close()
        session.close()


def register(subparsers: argparse._SubParsersAction) -> None:
    from shared.bus import BusConfig

    p = subparsers.add_parser("view", help="the live view of a running system in the browser (viser)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"HTTP port of the view (default {DEFAULT_PORT})")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (0.0.0.0: every interface)")
    BusConfig.add_cli_args(p)
    p.set_defaults(func=_view)


def _view(args: argparse.Namespace) -> int:
    from shared.bus import BusConfig

    def ready(view: LiveView) -> None:
        print(f"live view: {view.url}  (Ctrl-C to stop)", flush=True)

    try:
        serve(BusConfig.from_args(args, connect_timeout_ms=5000), args.port, args.host, ready=ready)
    except KeyboardInterrupt:
        pass
    return 0


def main(argv: list[str] | None = None) -> int:
    """`python -m cli.view`: what the launcher starts for `gd2p up --view`."""
    parser = argparse.ArgumentParser(prog="gd2p-view")
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(["view", *(argv or [])])
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    return int(args.func(args))


if __name__ == "__main__":
    import sys

    sys.exit(main(sys.argv[1:]))

"""`gd2p confirm ID` and `gd2p confirm --list`: release a plan the robot bridge holds (`gd2p up --confirm`).

    gd2p confirm --list [bus flags]                      the plans waiting now (id, robot, length, time left)
    gd2p confirm ID [--operator NAME] [bus flags]        run held command ID now

Exit codes: 0 the plan was released (or --list ran), 1 the bridge refused the confirmation (unknown id,
expired, already confirmed, dropped: the reason is printed), 2 no bridge answered (none runs with
--confirm, no router, or, under the secure profile, this session is not the operator identity: pass
`--zenoh-config <secure dir>/operator.json5`).
"""
from __future__ import annotations

import argparse
import getpass
import sys
import time

CLI_CONNECT_TIMEOUT_MS = 3000


def register(subparsers: argparse._SubParsersAction) -> None:
    from shared.bus import BusConfig

    parser = subparsers.add_parser(
        "confirm", help="release a plan the robot bridge holds (gd2p up --confirm), or --list them",
        description="With confirm on (gd2p up --confirm; the default for a hardware bridge) the robot bridge holds "
                    "each plan until an operator confirms it. Under the secure profile only the operator identity "
                    "may confirm.")
    parser.add_argument("command_id", nargs="?", metavar="ID", help="the held command's id (see --list)")
    parser.add_argument("--list", action="store_true", help="list the plans waiting for confirmation")
    parser.add_argument("--operator", default=None, help="who confirms, recorded with the plan (default: your user name)")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the bridge (default %(default)s)")
    BusConfig.add_cli_args(parser)
    parser.set_defaults(func=run_confirm)


def run_confirm(args: argparse.Namespace) -> int:
    if not args.list and not args.command_id:
        print("gd2p confirm: give the ID of a held plan, or --list", file=sys.stderr)
        return 2
    from client.confirm import ConfirmError, confirm, held_plans
    from shared.bus import BusConfig, BusError, open_session

    try:
        with open_session(BusConfig.from_args(args, connect_timeout_ms=CLI_CONNECT_TIMEOUT_MS)) as session:
            if args.list:
                return _print_held(held_plans(session))
            reply = confirm(session, args.command_id, operator=args.operator or getpass.getuser(),
                            timeout_s=args.timeout)
    except (BusError, ConfirmError) as exc:
        print(f"gd2p confirm: {exc}", file=sys.stderr)
        return 2
    if reply.accepted:
        print(f"{reply.command_id}: {reply.reason}; the plan runs now")
        return 0
    print(f"gd2p confirm: not accepted: {reply.reason}", file=sys.stderr)
    return 1


def _print_held(held: list) -> int:
    if not held:
        print("no plan is waiting for confirmation (the bridge announces held plans every second)")
        return 0
    rows = [("ID", "ROBOT", "WAYPOINTS", "DURATION_S", "EXPIRES_IN_S")]
    for h in held:
        times = h.plan.times_s.to_numpy()
        rows.append((h.command_id, f"{h.plan.arm}+{h.plan.hand}", str(len(times)),
                     f"{float(times[-1]):.1f}" if len(times) else "0", f"{h.expires_at - time.time():.0f}"))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip())
    return 0

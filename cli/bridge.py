"""`gd2p bridge selftest [--json] [--device D ...]` and `gd2p bridge estop [--reason TEXT]`.

selftest: every hardware robot against its protocol fake (shared/execution/selftest.py); devices are
named as everywhere else: panda (the Franka FR3), xarm7, leap, allegro. Exit code 0 only if every
device checked is ok.
estop: publish an EStop on `gd2p/robot_bridge/estop`: every robot of every bridge stops at once.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    from shared.execution.robots import DEVICES

    bridge = subparsers.add_parser("bridge", help="robot bridge: hardware self-test, e-stop")
    commands = bridge.add_subparsers(dest="bridge_command", metavar="SUBCOMMAND")
    commands.required = True
    selftest = commands.add_parser("selftest", help="exercise the panda (Franka FR3), xarm7, leap and allegro robots "
                                   "without hardware")
    selftest.add_argument("--json", action="store_true", help="print one JSON object (last line)")
    selftest.add_argument("--device", action="append", choices=list(DEVICES),
                          help="check only this device (repeatable; default all four)")
    selftest.set_defaults(func=_selftest)
    estop = commands.add_parser("estop", help="stop every robot now")
    estop.add_argument("--reason", default="operator e-stop", help="recorded with the stop")
    from shared.bus import BusConfig

    BusConfig.add_cli_args(estop)
    estop.set_defaults(func=_estop)


@contextlib.contextmanager
def _stdout_to_stderr():
    """Vendor SDKs print to stdout (some from C++): keep stdout for our JSON by pointing fd 1 at stderr."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _selftest(args: argparse.Namespace) -> int:
    from shared.execution.selftest import DEVICES, run_selftest

    devices = tuple(args.device) if args.device else DEVICES
    with _stdout_to_stderr():
        results = run_selftest(devices)
    if args.json:
        print(json.dumps(results))
    else:
        for device, result in results.items():
            detail = (f"final joint error {result['final_joint_error_rad']:.4f} rad, stop {'ok' if result['stop_ok'] else 'FAILED'}"
                      if "final_joint_error_rad" in result else "")
            print(f"{device:8s} {'ok  ' if result['ok'] else 'FAIL'} {detail} {result.get('reason', '')}".rstrip())
    return 0 if all(r["ok"] for r in results.values()) else 1


def _estop(args: argparse.Namespace) -> int:
    import getpass

    from shared.bus import BusConfig, BusError, open_session
    from shared.bus.keys import ROBOT_ESTOP_KEY as ESTOP_KEY
    from shared.contracts.codec import encode
    from shared.contracts.messages import EStop

    payload, encoding = encode(EStop(reason=args.reason, issued_by=getpass.getuser()))
    try:
        with open_session(BusConfig.from_args(args, connect_timeout_ms=5000)) as session:
            session.put(ESTOP_KEY, payload, encoding=encoding)
    except BusError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"e-stop sent on {ESTOP_KEY}: {args.reason}")
    return 0

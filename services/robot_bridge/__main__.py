"""`python -m services.robot_bridge [bus flags] [--worker-id ID] [--hardware ARM+HAND ... | --robot sim|mujoco
[--tracking image|truth]] [--confirm | --no-confirm] [--confirm-timeout S]`: run the robot bridge until SIGTERM.

Without --hardware it drives the simulated robot: PyBullet's (`--robot sim`, the default), or MuJoCo's
(`--robot mujoco`: plans are still made in PyBullet, so they execute in physics nobody tuned them to;
MUJOCO_GL defaults to egl there, for its headless depth cameras), seeing the object through its rendered depth
cameras (`--tracking truth`: the simulator's pose plus noise instead); with --hardware, the real devices. --confirm holds each
plan until an operator confirms it (`gd2p confirm ID`) within --confirm-timeout seconds: the default with
--hardware (--no-confirm turns it off, with a warning), off for the simulated robot.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys

from services.robot_bridge.service import run
from shared.bus import BusConfig
from shared.bus.service_cli import configure_service_logging, service_arg_parser
from shared.execution.confirm import DEFAULT_TIMEOUT_S, MAX_TIMEOUT_S
from shared.execution.hardware import HardwareConfigError, HardwareSpec
from shared.execution.robot import RobotError
from shared.execution.robots import SIM_ROBOTS, TRACKING_MODES


def main(argv: list[str] | None = None) -> int:
    parser = service_arg_parser("robot_bridge", __doc__)
    HardwareSpec.add_cli_args(parser)
    add_confirm_args(parser)
    add_robot_arg(parser)
    args = parser.parse_args(argv)
    try:
        hardware = HardwareSpec.from_args(args)  # every address given? (connecting happens in run)
    except HardwareConfigError as exc:
        parser.error(str(exc))
    if hardware is not None and args.robot != "sim":
        parser.error(f"--robot {args.robot} chooses the simulated robot's engine; --hardware drives the real devices")
    if hardware is not None and args.tracking != "image":
        parser.error("--tracking chooses how the simulated robot sees the object; with --hardware your tracker does")
    if args.robot == "mujoco":
        # MuJoCo reads MUJOCO_GL when it is first imported (in `run`): a service has no display, EGL renders
        # headless. An operator's own setting (osmesa where EGL is missing) is kept.
        os.environ.setdefault("MUJOCO_GL", "egl")
    if not 0.0 < args.confirm_timeout <= MAX_TIMEOUT_S:
        parser.error(f"--confirm-timeout must be in (0, {MAX_TIMEOUT_S:g}] s (the planner waits 300 s for a command)")
    configure_service_logging()
    confirm = args.confirm if args.confirm is not None else hardware is not None
    if hardware is not None and not confirm:
        logging.getLogger("gd2p.robot_bridge").warning(
            "--no-confirm on hardware: every plan that passes the checks moves the robot at once, without an "
            "operator's confirmation")
    try:
        run(BusConfig.from_args(args), worker_id=args.worker_id, hardware=hardware,
            confirm_timeout_s=args.confirm_timeout if confirm else None, robot=args.robot, tracking=args.tracking)
    except RobotError as exc:
        print(f"robot_bridge: cannot drive the hardware: {exc}", file=sys.stderr)
        return 1
    return 0


def add_confirm_args(parser: argparse.ArgumentParser) -> None:
    """--confirm / --no-confirm (default: on with --hardware, off for the simulated robot), --confirm-timeout S."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--confirm", dest="confirm", action="store_true", default=None,
                       help="hold each plan until an operator confirms it (gd2p confirm ID); default with --hardware")
    group.add_argument("--no-confirm", dest="confirm", action="store_false",
                       help="run plans without confirmation, also on hardware (warned)")
    parser.add_argument("--confirm-timeout", type=float, default=DEFAULT_TIMEOUT_S, metavar="S",
                        help=f"drop a plan not confirmed within S seconds (default {DEFAULT_TIMEOUT_S:g}, at most "
                             f"{MAX_TIMEOUT_S:g}); the push answers not_confirmed")


def add_robot_arg(parser: argparse.ArgumentParser) -> None:
    """--robot sim|mujoco: the simulated robot's engine, --tracking image|truth: how it sees the object (without
    --hardware)."""
    parser.add_argument("--robot", choices=SIM_ROBOTS, default="sim",
                        help="the simulated robot's physics engine: sim (PyBullet, the planner's own; default) or "
                             "mujoco (MuJoCo: plans made in PyBullet execute in an engine nobody tuned them to)")
    parser.add_argument("--tracking", choices=TRACKING_MODES, default="image",
                        help="how the simulated robot sees the object while it pushes: image (its model registered in "
                             "the depth frames the engine renders, arm and hand in view; default) or truth (the "
                             "simulator's pose plus a little noise: quicker, for work on the planner)")


if __name__ == "__main__":
    sys.exit(main())

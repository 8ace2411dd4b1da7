"""`python -m services.robot_bridge [bus flags] [--worker-id ID] [--hardware ARM+HAND ...]`: run the robot bridge until SIGTERM.

Without --hardware it drives the simulated robot (PyBullet); with it, the real devices.
"""
from __future__ import annotations

import sys

from services.robot_bridge.service import run
from shared.bus import BusConfig
from shared.bus.service_cli import configure_service_logging, service_arg_parser
from shared.execution.hardware import HardwareConfigError, HardwareSpec
from shared.execution.robot import RobotError


def main(argv: list[str] | None = None) -> int:
    parser = service_arg_parser("robot_bridge", __doc__)
    HardwareSpec.add_cli_args(parser)
    args = parser.parse_args(argv)
    try:
        hardware = HardwareSpec.from_args(args)  # every address given? (connecting happens in run)
    except HardwareConfigError as exc:
        parser.error(str(exc))
    configure_service_logging()
    try:
        run(BusConfig.from_args(args), worker_id=args.worker_id, hardware=hardware)
    except RobotError as exc:
        print(f"robot_bridge: cannot drive the hardware: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""`python -m services.robot_bridge [bus flags] [--worker-id ID] [--hardware ARM+HAND ...]`: run the robot bridge until SIGTERM.

Without --hardware it drives the simulated robot (PyBullet); with it, the real devices.
"""
from __future__ import annotations

import argparse
import logging
import sys

from services.robot_bridge.backend import BackendError
from services.robot_bridge.hardware import HardwareConfigError, HardwareSpec
from services.robot_bridge.service import run
from shared.bus import BusConfig


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.robot_bridge", description=__doc__)
    BusConfig.add_cli_args(parser)
    parser.add_argument("--worker-id", default=None, help="unique id on the bus (default: host-pid-random)")
    HardwareSpec.add_cli_args(parser)
    args = parser.parse_args(argv)
    try:
        hardware = HardwareSpec.from_args(args)
        if hardware is not None:
            hardware.devices()  # every address given? (connecting happens in run)
    except HardwareConfigError as exc:
        parser.error(str(exc))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        run(BusConfig.from_args(args), worker_id=args.worker_id, hardware=hardware)
    except BackendError as exc:
        print(f"robot_bridge: cannot drive the hardware: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

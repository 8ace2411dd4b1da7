"""`python -m services.robot_bridge [bus flags] [--worker-id ID]`: run one robot_bridge worker until SIGTERM."""
from __future__ import annotations

import argparse
import logging
import sys

from services.robot_bridge.service import run
from shared.bus import BusConfig


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.robot_bridge", description=__doc__)
    BusConfig.add_cli_args(parser)
    parser.add_argument("--worker-id", default=None, help="unique id on the bus (default: host-pid-random)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    run(BusConfig.from_args(args), worker_id=args.worker_id)
    return 0


if __name__ == "__main__":
    sys.exit(main())

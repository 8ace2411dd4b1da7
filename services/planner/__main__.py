"""`python -m services.planner [bus flags] [--worker-id ID] [--record-dir DIR]`: run one planner worker until SIGTERM."""
from __future__ import annotations

import argparse
import logging
import sys

from services.planner.service import run
from shared.bus import BusConfig


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.planner", description=__doc__)
    BusConfig.add_cli_args(parser)
    parser.add_argument("--worker-id", default=None, help="unique id on the bus (default: host-pid-random)")
    parser.add_argument("--record-dir", default=None,
                        help="where each push's MCAP and storyboard go (default: $GD2P_PUSH_RECORD_DIR or recordings/pushes)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    run(BusConfig.from_args(args), worker_id=args.worker_id, record_dir=args.record_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())

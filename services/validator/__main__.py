"""`python -m services.validator [bus flags] [--worker-id ID]`: run one validator worker until SIGTERM."""
from __future__ import annotations

import argparse
import logging
import sys

from services.validator.service import SERVICE, handlers
from shared.bus import BusConfig, run_worker


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.validator", description=__doc__)
    BusConfig.add_cli_args(parser)
    parser.add_argument("--worker-id", default=None, help="unique id on the bus (default: host-pid-random)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    run_worker(SERVICE, handlers(), BusConfig.from_args(args), worker_id=args.worker_id)
    return 0


if __name__ == "__main__":
    sys.exit(main())

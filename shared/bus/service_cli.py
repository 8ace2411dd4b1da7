"""The command line every service process shares: `python -m services.X [bus flags] [--worker-id ID] ...`."""
from __future__ import annotations

import argparse
import logging


def service_arg_parser(service: str, description: str | None) -> argparse.ArgumentParser:
    """A parser with the bus flags and --worker-id; a service adds its own flags to it."""
    from shared.bus.config import BusConfig

    parser = argparse.ArgumentParser(prog=f"python -m services.{service}", description=description)
    BusConfig.add_cli_args(parser)
    parser.add_argument("--worker-id", default=None, help="unique id on the bus (default: host-pid-random)")
    return parser


def configure_service_logging() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")

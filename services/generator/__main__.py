"""`python -m services.generator [bus flags] [--worker-id ID]`: run one generator worker until SIGTERM."""
from __future__ import annotations

import sys

from services.generator.service import SERVICE, handlers, job_budget
from shared.bus import BusConfig, run_worker
from shared.bus.service_cli import configure_service_logging, service_arg_parser


def main(argv: list[str] | None = None) -> int:
    parser = service_arg_parser("generator", __doc__)
    args = parser.parse_args(argv)
    configure_service_logging()
    run_worker(SERVICE, handlers(), BusConfig.from_args(args), worker_id=args.worker_id, job_budget=job_budget)
    return 0


if __name__ == "__main__":
    sys.exit(main())

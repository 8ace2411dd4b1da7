"""`python -m services.validator [bus flags] [--worker-id ID]`: run one validator worker until SIGTERM."""
from __future__ import annotations

import sys

from shared.bus import BusConfig, run_worker
from shared.bus.service_cli import configure_service_logging, service_arg_parser
from shared.validation.jobs import JOB_DEADLINE_S, SERVICE, handlers, is_express, job_budget


def main(argv: list[str] | None = None) -> int:
    parser = service_arg_parser("validator", __doc__)
    args = parser.parse_args(argv)
    configure_service_logging()
    run_worker(SERVICE, handlers(), BusConfig.from_args(args), worker_id=args.worker_id, job_deadline_s=JOB_DEADLINE_S,
               job_budget=job_budget, express=is_express)
    return 0


if __name__ == "__main__":
    sys.exit(main())

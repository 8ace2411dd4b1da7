"""`python -m services.planner [bus flags] [--worker-id ID] [--record-dir DIR]`: run one planner worker until SIGTERM."""
from __future__ import annotations

import sys

from services.planner.service import run
from shared.bus import BusConfig
from shared.bus.service_cli import configure_service_logging, service_arg_parser


def main(argv: list[str] | None = None) -> int:
    parser = service_arg_parser("planner", __doc__)
    parser.add_argument("--record-dir", default=None,
                        help="where each push's MCAP and storyboard go (default: $GD2P_PUSH_RECORD_DIR or recordings/pushes)")
    args = parser.parse_args(argv)
    configure_service_logging()
    run(BusConfig.from_args(args), worker_id=args.worker_id, record_dir=args.record_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())

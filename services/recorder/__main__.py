"""`python -m services.recorder`: record the bus to MCAP until SIGTERM / Ctrl-C."""
from __future__ import annotations

import argparse
import json
import logging
import math
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

from services.recorder.service import RecorderService
from shared.bus import BusConfig, BusError, open_session
from visualisation.recorder import DEFAULT_MAX_FILE_MB, MIB, RecorderError, RotatingRecorder


def _positive_mb(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):  # nan and inf too
        raise argparse.ArgumentTypeError(f"must be a positive number of megabytes, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m services.recorder", description="Record every gd2p/** sample to rotating MCAP files.")
    BusConfig.add_cli_args(parser)
    parser.add_argument("--record-dir", required=True, help="directory for gd2p-<UTC time>-<seq>.mcap files")
    parser.add_argument("--max-file-mb", type=_positive_mb, default=DEFAULT_MAX_FILE_MB, help="start a new file past this size (default %(default)s)")
    parser.add_argument("--worker-id", default=None, help="worker id of the liveliness token (default host-pid-random)")
    parser.add_argument("--key-expr", default="gd2p/**", help="what to record (default %(default)s)")
    parser.add_argument("--run-seeds", default=os.environ.get(SEEDS_ENV, ""), metavar="TEXT",
                        help=f"the run's seeds, written into every file's metadata (default: ${SEEDS_ENV}, "
                             "else 'not given')")
    return parser


SEEDS_ENV = "GD2P_RUN_SEEDS"
COMMIT_ENV = "GD2P_COMMIT"  # where there is no git checkout (a container image)


def current_commit() -> str:
    """$GD2P_COMMIT, else `git rev-parse HEAD` of this code's checkout, else 'unknown'."""
    if os.environ.get(COMMIT_ENV):
        return os.environ[COMMIT_ENV]
    try:
        done = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parents[2],
                              capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return done.stdout.strip() if done.returncode == 0 and done.stdout.strip() else "unknown"


def run_info(args: argparse.Namespace, cfg: BusConfig) -> dict[str, str]:
    """What each file's metadata says of the run: commit, the recorder's config, the run's seeds."""
    config = {"record_dir": str(args.record_dir), "max_file_mb": args.max_file_mb, "key_expr": args.key_expr,
              "worker_id": args.worker_id, "bus": cfg.describe()}
    return {"commit": current_commit(), "config": json.dumps(config, sort_keys=True),
            "seeds": args.run_seeds or "not given"}


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        cfg = BusConfig.from_args(args)
        recorder = RotatingRecorder(args.record_dir, int(args.max_file_mb * MIB), run_info=run_info(args, cfg))
        with open_session(cfg) as session:
            # From here on a SIGTERM must end in a drained, closed file, not a killed process.
            stop = threading.Event()
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, lambda signum, frame: stop.set())
            RecorderService(recorder, args.key_expr).run(session, worker_id=args.worker_id, stop=stop)
    except (RecorderError, BusError) as exc:
        print(f"recorder: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""`gd2p replay FILE.mcap ...`: republish a recording on the bus, each sample on its key with its encoding."""
from __future__ import annotations

import argparse
import itertools
import os
import sys
import time

from cli.args import non_negative_float
from visualisation.recording import Record, RecordingError, read_records, replay

CLI_CONNECT_TIMEOUT_MS = 5000


def register(subparsers: argparse._SubParsersAction) -> None:
    from shared.bus import BusConfig

    parser = subparsers.add_parser("replay", help="republish an MCAP recording on the bus", description=__doc__)
    parser.add_argument("files", nargs="+", metavar="FILE.mcap", help="recording(s), replayed one after the other")
    parser.add_argument("--rate", type=non_negative_float, default=1.0, help="speed factor; 0 = as fast as possible (default %(default)s)")
    parser.add_argument("--keys", default="gd2p/**", metavar="KEYEXPR", help="replay only samples whose key matches (default %(default)s)")
    BusConfig.add_cli_args(parser)
    parser.set_defaults(func=run_replay)


def run_replay(args: argparse.Namespace) -> int:
    import zenoh

    from shared.bus import BusConfig, BusError, open_session

    if args.rate < 0:
        print(f"gd2p replay: --rate must be >= 0, got {args.rate}", file=sys.stderr)
        return 2
    missing = [path for path in args.files if not os.path.isfile(path)]
    if missing:
        print(f"gd2p replay: no such recording: {', '.join(missing)}", file=sys.stderr)
        return 2
    try:
        wanted = zenoh.KeyExpr(args.keys)
    except zenoh.ZError as exc:
        print(f"gd2p replay: --keys {args.keys!r} is not a key expression: {exc}", file=sys.stderr)
        return 2
    records = (
        record
        for record in itertools.chain.from_iterable(read_records(path) for path in args.files)
        if wanted.intersects(zenoh.KeyExpr(record.key))
    )
    keys: set[str] = set()
    started = time.monotonic()
    try:
        with open_session(BusConfig.from_args(args, connect_timeout_ms=CLI_CONNECT_TIMEOUT_MS)) as session:

            def publish(record: Record) -> None:
                session.put(record.key, record.payload, encoding=record.encoding)
                keys.add(record.key)

            count = replay(records, publish, args.rate)
    except (RecordingError, BusError) as exc:
        print(f"gd2p replay: {exc}", file=sys.stderr)
        return 1
    print(f"replayed {count} messages on {len(keys)} keys in {time.monotonic() - started:.2f} s")
    return 0

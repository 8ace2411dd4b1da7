"""`gd2p replay FILE.mcap ...`: republish a recording on the bus, each sample on its key with its encoding.
`gd2p replay FILE.mcap --view [--port PORT]`: play it in the live view instead (no bus), with pause and speed.
`gd2p replay FILE.mcap --resim`: plan a push recording's request again in this process (no bus) and say
whether the same plan comes out, bit for bit (exit 0 identical, 1 different, 2 an unusable recording).
`gd2p recording-info FILE.mcap ...`: what the recorder counted (received, missing) and the run it recorded.
"""
from __future__ import annotations

import argparse
import itertools
import json
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
    parser.add_argument("--view", action="store_true",
                        help="play the recording in the live view (browser; pause and speed controls) instead of the bus")
    parser.add_argument("--port", type=int, default=None, help="the view's HTTP port (with --view; default 8090)")
    parser.add_argument("--exit", action="store_true", help="with --view: stop serving when the recording is played")
    parser.add_argument("--resim", action="store_true",
                        help="re-decide a push recording (push-<id>.mcap): plan its request again in this process "
                             "and compare the plans bit for bit; exit 0 identical, 1 different, 2 unusable")
    BusConfig.add_cli_args(parser)
    parser.set_defaults(func=run_replay)

    info = subparsers.add_parser(
        "recording-info", help="received / missing counts and run facts of MCAP recordings",
        description="Print what the recorder wrote into each file's metadata: the commit, config and seeds of the "
                    "run, and per key and publisher the samples received and missing (gaps in the publisher's "
                    "sequence numbers). Exit code 1 if any file counts a missing sample.")
    info.add_argument("files", nargs="+", metavar="FILE.mcap", help="recording(s)")
    info.add_argument("--streams", action="store_true", help="one line per key and publisher, not only those missing some")
    info.add_argument("--json", action="store_true", help="one JSON object per file")
    info.set_defaults(func=run_info)


def run_info(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from visualisation.recorder import read_counts

    missing_any = False
    for path in args.files:
        try:
            counts = read_counts(path)
        except RecordingError as exc:
            print(f"gd2p recording-info: {exc}", file=sys.stderr)
            return 2
        streams = {"file": counts.file, **({"total": counts.total} if counts.total is not None else {})}
        missing_any |= any(c.missing for c in counts.file.values())
        if args.json:
            print(json.dumps({"path": str(path), "recording": counts.recording,
                              **{part: [{"key": k, "publisher": p, **asdict(c)} for (k, p), c in sorted(each.items())]
                                 for part, each in streams.items()}}))
            continue
        if not counts.counted:
            print(f"{path}: no counts in its metadata (an older recording, or recovered after its recorder died)")
            continue
        run = counts.recording
        final = " (the run's last)" if run.get("final") == "true" else ""
        print(f"{path}: file {run.get('file_index', '?')}{final}; commit {run.get('commit', 'unknown')}; "
              f"seeds {run.get('seeds', 'not given')}")
        for part, each in streams.items():
            received = sum(c.received for c in each.values())
            missing = sum(c.missing for c in each.values())
            late = sum(c.late for c in each.values())
            unnumbered = sum(c.received for (_k, p), c in each.items() if not p)
            what = "this file" if part == "file" else "whole run"
            print(f"  {what}: received {received}, missing {missing}" + (f", late {late}" if late else "")
                  + f" ({unnumbered} without sequence numbers) on {len({k for k, _p in each})} keys")
            for (key, publisher), c in sorted(each.items()):
                if args.streams or c.missing or c.late:
                    seqs = f", seq {c.first_seq}..{c.last_seq}" if c.first_seq is not None else ""
                    print(f"    {key} [{publisher or 'unnumbered'}]: received {c.received}, missing {c.missing}"
                          + (f", late {c.late}" if c.late else "") + seqs)
    return 1 if missing_any else 0


def run_resim(args: argparse.Namespace) -> int:
    """Each file: plan again, compare; the worst exit code (2 unusable > 1 different > 0 identical)."""
    from evaluation.resim import UnusableRecording, resim

    worst = 0
    for path in args.files:
        print(f"{path}: planning the recorded request again ...", flush=True)
        try:
            result = resim(path)
        except UnusableRecording as exc:
            print(f"gd2p replay --resim: unusable recording: {exc}", file=sys.stderr)
            worst = 2
            continue
        for warning in result.warnings:
            print(f"warning: {warning}", file=sys.stderr)
        pushes = len(result.recorded)
        if result.identical:
            print(f"{path}: identical: the same plan comes out ({pushes} push(es), every waypoint bit for bit)")
            continue
        print(f"{path}: DIFFERENT: planning again gives another decision")
        for difference in result.differences:
            print(f"  {difference}")
        worst = max(worst, 1)
    return worst


def run_replay(args: argparse.Namespace) -> int:
    import zenoh

    if getattr(args, "resim", False):
        return run_resim(args)

    from shared.bus import BusConfig, BusError, RecordedPublisher, open_session

    if args.rate < 0:
        print(f"gd2p replay: --rate must be >= 0, got {args.rate}", file=sys.stderr)
        return 2
    missing = [path for path in args.files if not os.path.isfile(path)]
    if missing:
        print(f"gd2p replay: no such recording: {', '.join(missing)}", file=sys.stderr)
        return 2
    if args.view:
        return _replay_in_view(args)
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
    publishers: dict[str, RecordedPublisher] = {}
    started = time.monotonic()
    try:
        with open_session(BusConfig.from_args(args, connect_timeout_ms=CLI_CONNECT_TIMEOUT_MS)) as session:

            def publish(record: Record) -> None:
                if record.key not in publishers:  # one numbered, blocking publisher per key (shared/bus/recorded.py)
                    publishers[record.key] = RecordedPublisher(session, record.key)
                publishers[record.key].put(record.payload, encoding=record.encoding)

            try:
                count = replay(records, publish, args.rate)
            finally:
                for publisher in publishers.values():
                    publisher.close()
    except (RecordingError, BusError) as exc:
        print(f"gd2p replay: {exc}", file=sys.stderr)
        return 1
    print(f"replayed {count} messages on {len(publishers)} keys in {time.monotonic() - started:.2f} s")
    return 0


def _replay_in_view(args: argparse.Namespace) -> int:
    from visualisation.live import DEFAULT_PORT, LiveView
    from visualisation.live_replay import ReplayPlayer

    view = LiveView(port=args.port or DEFAULT_PORT, title="GD2P replay")
    print(f"live view: {view.url}  (Ctrl-C to stop)", flush=True)
    try:
        player = ReplayPlayer(view, args.files, speed=args.rate if args.rate > 0 else 10.0)
        count = player.play()
        print(f"played {count} messages in the view")
        if not args.exit:
            while True:  # keep serving: the view's Restart plays it again
                if player.restart_requested.wait(1.0):
                    player.play()
    except KeyboardInterrupt:
        pass
    except RecordingError as exc:
        print(f"gd2p replay: {exc}", file=sys.stderr)
        return 1
    finally:
        view.close()
    return 0

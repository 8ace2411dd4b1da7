"""`gd2p objects list [--split S] [--json]`: the object library with class, source, size and split."""
from __future__ import annotations

import argparse
import json
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    objects = subparsers.add_parser("objects", help="the object library")
    commands = objects.add_subparsers(dest="objects_command", metavar="SUBCOMMAND")
    commands.required = True
    listing = commands.add_parser(
        "list",
        help="list library objects (id, class, source, size, split)",
        description="List library objects. The first run describes the non-procedural objects once "
        "(tens of seconds) and caches the result under $GD2P_CACHE_DIR.",
    )
    listing.add_argument("--split", choices=("train", "val", "test"),
                         help="only objects of this split (test: the development split's objects; the final split's "
                              "objects are not library objects and are never listed)")
    listing.add_argument("--json", action="store_true", help="print a JSON object instead of a table")
    listing.set_defaults(func=_list)


def _list(args: argparse.Namespace) -> int:
    from shared.world.objects import list_objects

    infos = list_objects(args.split, progress=sys.stderr.isatty())
    if args.json:
        print(json.dumps({"split": args.split, "count": len(infos), "objects": [info.to_dict() for info in infos]}))
        return 0
    print(f"{'id':<20} {'class':<11} {'source':<13} {'size (cm)':<18} split")
    for info in infos:
        a, b, h = (100 * v for v in info.size_m)
        print(f"{info.id:<20} {info.shape_class:<11} {info.source:<13} {f'{a:.1f} x {b:.1f} x {h:.1f}':<18} {info.split}")
    print(f"{len(infos)} objects", file=sys.stderr)
    return 0

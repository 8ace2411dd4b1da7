"""`gd2p hands info NAME [--json]`: what the system knows about a hand model."""
from __future__ import annotations

import argparse
import json
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    hands = subparsers.add_parser("hands", help="hand models (Allegro, LEAP)")
    commands = hands.add_subparsers(dest="hands_command", metavar="SUBCOMMAND")
    commands.required = True
    info = commands.add_parser("info", help="joints, links, palm normal, contact candidates, collision primitives")
    info.add_argument("name", help="hand name: allegro or leap")
    info.add_argument("--json", action="store_true", help="print one JSON object")
    info.set_defaults(func=_info)


def hand_info(name: str) -> dict:
    """The `hands info` record for one hand (importable for other tools)."""
    from shared.robots.hands import load_hand  # heavy (torch, pytorch_kinematics): only when the command runs

    hand = load_hand(name)
    regions = hand.contact_candidates.indices_by_region()
    return {
        "name": hand.name,
        "dof": hand.dof,
        "urdf": str(hand.urdf_path),
        "contact_candidates": len(hand.contact_candidates),
        "contact_regions": {region: len(indices) for region, indices in regions.items()},
        "links": list(hand.link_names),
        "joint_names": list(hand.joint_names),
        "joint_limits": [[round(float(lo), 6), round(float(hi), 6)]
                         for lo, hi in zip(hand.joint_lower, hand.joint_upper, strict=True)],
        "open_joint_positions": [round(float(v), 6) for v in hand.open_joint_positions],
        "palm_normal": [round(float(v), 6) for v in hand.palm_normal_base],
        "collision_primitives": [prim.as_dict() for prim in hand.primitives.prims],
        "self_collision_keypoints": int(hand.keypoints.link_index.shape[0]),
        "self_collision_pairs": int(hand.keypoints.pairs.shape[0]),
    }


def _info(args: argparse.Namespace) -> int:
    from shared.robots.hands import HandModelError

    try:
        info = hand_info(args.name)
    except HandModelError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(info))
        return 0
    print(f"{info['name']}: {info['dof']} joints, {len(info['links'])} links, "
          f"{len(info['collision_primitives'])} collision primitives, {info['contact_candidates']} contact candidates")
    print(f"URDF: {info['urdf']}")
    print(f"palm normal (base frame): {info['palm_normal']}")
    print(f"\n{'joint':<12}{'lower':>9}{'upper':>9}{'open':>9}")
    for joint, (lower, upper), open_ in zip(info["joint_names"], info["joint_limits"], info["open_joint_positions"],
                                            strict=True):
        print(f"{joint:<12}{lower:>9.3f}{upper:>9.3f}{open_:>9.3f}")
    print(f"\n{'contact region':<28}{'candidates':>10}")
    for region, count in info["contact_regions"].items():
        print(f"{region:<28}{count:>10}")
    return 0

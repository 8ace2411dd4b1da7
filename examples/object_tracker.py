"""Publish an object's pose for the robot bridge, as a tracker beside real hardware does.

Written from docs/interfaces.md alone (it imports nothing of the project): an ObjectTrack msgpack map on
`gd2p/robot_bridge/object_track` at the tracker's rate. A bridge driving real hardware folds the latest
pose (if under 0.5 s old) into the ExecutionStates it publishes while a plan runs, where the planner's
closed-loop monitor (`gd2p push --closed-loop`) and its corrective pushes read it.

This one reports a fixed pose (say, of an object you have measured, to try the path end to end);
replace `read_pose` with your tracker (an RGB-D pose tracker, markers, motion capture). Under the
secure profile, run it with the "tracker" certificate: that identity may publish on this key only.
Like every recorded publisher it uses congestion control BLOCK and numbers its samples in the attachment
(msgpack `{"publisher": <id>, "seq": <n from 1>}`), so the recorder can count any it never got.

    python examples/object_tracker.py --connect tcp/127.0.0.1:7447 --position 0.55 0.0 0.04 --yaw 10
"""
import argparse
import json
import math
import sys
import time
import uuid

import msgpack
import zenoh

KEY = "gd2p/robot_bridge/object_track"
ENCODING = "application/msgpack;ObjectTrack"


def read_pose(args: argparse.Namespace) -> tuple[list[float], list[float]]:
    """The object's position (m) and xyzw quaternion in the robot's world frame, now."""
    half = math.radians(args.yaw) / 2.0
    return list(args.position), [0.0, 0.0, math.sin(half), math.cos(half)]


def track_message(position: list[float], quaternion_xyzw: list[float], source: str) -> dict:
    """An ObjectTrack as a msgpack map (docs/interfaces.md); command and plan time are the bridge's to add."""
    return {"schema_version": 1, "id": uuid.uuid4().hex, "stamp": time.time(),
            "pose": {"position": position, "quaternion_xyzw": quaternion_xyzw}, "source": source}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447", help="the router (default %(default)s)")
    parser.add_argument("--position", nargs=3, type=float, required=True, metavar=("X", "Y", "Z"),
                        help="the object's frame in the world, m")
    parser.add_argument("--yaw", type=float, default=0.0, help="about the world's vertical, degrees")
    parser.add_argument("--rate", type=float, default=20.0, help="poses per second (default %(default)s; 10-30)")
    parser.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C)")
    parser.add_argument("--source", default="example-tracker", help="the tracker's name in each message")
    args = parser.parse_args()
    if args.rate <= 0:
        parser.error("--rate must be positive")
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([args.connect]))
    config.insert_json5("scouting/multicast/enabled", "false")
    deadline = None if args.seconds is None else time.monotonic() + args.seconds
    with zenoh.open(config) as session:
        publisher = session.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
        publisher_id, seq = f"{args.source}.{uuid.uuid4().hex[:8]}", 0
        try:
            while deadline is None or time.monotonic() < deadline:
                position, quaternion = read_pose(args)
                payload = msgpack.packb(track_message(position, quaternion, args.source), use_bin_type=True)
                seq += 1
                publisher.put(payload, encoding=ENCODING, attachment=msgpack.packb({"publisher": publisher_id, "seq": seq}))
                time.sleep(1.0 / args.rate)
        except KeyboardInterrupt:
            pass
        publisher.undeclare()
    return 0


if __name__ == "__main__":
    sys.exit(main())

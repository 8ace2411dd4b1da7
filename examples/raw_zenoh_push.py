"""Push a box through a running GD2P system with nothing but zenoh and msgpack.

Written from docs/interfaces.md alone (it imports nothing of the project): find a live planner by its
liveliness token, hold a client lease (a liveliness token the planner watches: without one it refuses a
request that would move the robot, and when it goes the request is cancelled), build a PushRequest as a
msgpack map naming that lease, query that planner's own job key, decode the reply (a PushResponse, or an
ErrorReply).

    gd2p up &                                                     # or any running system
    python examples/raw_zenoh_push.py --connect tcp/127.0.0.1:7447
"""
import argparse
import json
import sys
import uuid

import msgpack
import zenoh

ENCODING = "application/msgpack;"  # + the message type


def open_session(endpoint: str) -> zenoh.Session:
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


def find_planner(session: zenoh.Session) -> str:
    """The worker id of a live planner: the last chunk of its token gd2p/alive/planner/<worker_id>."""
    for reply in session.liveliness().get("gd2p/alive/planner/*", timeout=5.0):
        if reply.ok is not None:
            return str(reply.ok.key_expr).rsplit("/", 1)[1]
    sys.exit("no planner is alive: is the system running?")


def ask(session: zenoh.Session, key: str, message: str, fields: dict, timeout_s: float) -> tuple[str, dict]:
    """Query one worker's key with a message; (type, fields) of its reply."""
    replies = session.get(key, payload=msgpack.packb(fields, use_bin_type=True), encoding=ENCODING + message,
                          consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s,
                          attachment=msgpack.packb({"timeout_s": timeout_s}))
    for reply in replies:
        if reply.ok is not None:
            reply_type = str(reply.ok.encoding).removeprefix(ENCODING)
            return reply_type, msgpack.unpackb(reply.ok.payload.to_bytes(), raw=False)
    sys.exit(f"no answer on {key} within {timeout_s:.0f} s")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447", help="the router (default %(default)s)")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds to wait for the push (default %(default)s)")
    args = parser.parse_args()
    # Held while we wait (closing the session cancels the push); <identity>/<holder>: the secure profile lets
    # the "cli" certificate hold only gd2p/lease/client/cli/*.
    lease = f"gd2p/lease/client/cli/{uuid.uuid4().hex[:16]}"
    request = {  # a PushRequest (schema 2): every field left out takes its default
        "schema_version": 2,
        "id": uuid.uuid4().hex,
        "object": {"library_id": "proc-box-013"},
        "direction_deg": 90.0,
        "client_lease": lease,
        "options": {"method": "fixed"},  # the planner's knobs; those left out take the planner's default
    }
    with open_session(args.connect) as session:
        token = session.liveliness().declare_token(lease)
        planner = find_planner(session)
        print(f"planner: {planner}")
        reply_type, reply = ask(session, f"gd2p/planner/worker/{planner}/job", "PushRequest", request, args.timeout)
        token.undeclare()
    if reply_type == "ErrorReply":
        print(f"error {reply['code']}: {reply['message']}")
        return 1
    x, y, z = reply["result"]["final_object_pose"]["position"]
    print(f"success: {reply['success']}")
    print(f"final object position: {x:.3f} {y:.3f} {z:.3f}")
    return 0 if reply["success"] else 1


if __name__ == "__main__":
    sys.exit(main())

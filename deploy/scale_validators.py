"""Bring a running GD2P system to exactly N validator workers.

    python deploy/scale_validators.py N [--connect tcp/127.0.0.1:7447]   # a local `gd2p up`
    python deploy/scale_validators.py N --compose                          # the docker compose system

Local: sends a `ScaleRequest` to the launcher's control key (`gd2p/launcher/control`); the
launcher starts or stops validator processes and answers once the new ones have registered. It
refuses N above its configured maximum (8 validators on 2 cores by default; `GD2P_MAX_SCALE` when
starting `gd2p up`). Under `gd2p up --secure` only the operator identity reaches the control key:
add `--zenoh-config gd2p-secure/client-operator.json5` (the "cli" certificate gets no answer).
Compose: runs `docker compose -f deploy/docker-compose.yml up -d --no-recreate --scale validator=N`.
Validators on other machines join the same farm by connecting to the router themselves
(`python -m services.validator --connect tcp/<router-host>:7447`); they are not counted here.
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the project importable without installing it
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

COMPOSE_FILE = Path(__file__).resolve().with_name("docker-compose.yml")
CONNECT_TIMEOUT_MS = 3000


def compose_scale_command(count: int, compose_file: Path = COMPOSE_FILE) -> list[str]:
    """The docker compose invocation that runs exactly `count` validator containers."""
    if count < 0:
        raise ValueError(f"the number of validators must be >= 0, got {count}")
    return ["docker", "compose", "-f", str(compose_file), "up", "-d", "--no-recreate", "--scale", f"validator={count}"]


def scale_with_compose(count: int) -> int:
    cmd = compose_scale_command(count)
    if shutil.which(cmd[0]) is None:
        print("scale_validators: `docker` is not installed here; cannot use --compose", file=sys.stderr)
        return 1
    print("+ " + " ".join(cmd), flush=True)
    result = subprocess.run(cmd)
    if result.returncode != 0:
        print(f"scale_validators: docker compose failed (exit code {result.returncode}); is the Docker engine "
              f"running and the compose plugin installed?", file=sys.stderr)
    return result.returncode


def scale_local(count: int, args: argparse.Namespace) -> int:
    from deploy.launcher import LaunchError, request_scale
    from shared.bus import BusConfig, BusError, RemoteError, open_session

    try:
        with open_session(BusConfig.from_args(args, connect_timeout_ms=CONNECT_TIMEOUT_MS)) as session:
            reply = request_scale(session, "validator", count, timeout=args.timeout)
    except (BusError, LaunchError, RemoteError) as exc:
        print(f"scale_validators: {exc}", file=sys.stderr)
        return 1
    changes = [f"started {', '.join(reply.started)}" if reply.started else "",
               f"stopped {', '.join(reply.stopped)}" if reply.stopped else ""]
    print(f"validators: {reply.count} ({'; '.join(c for c in changes if c) or 'no change'})")
    return 0


def main(argv: list[str] | None = None) -> int:
    from shared.bus import BusConfig

    parser = argparse.ArgumentParser(prog="scale_validators.py", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("count", type=int, metavar="N", help="the number of validator workers wanted")
    parser.add_argument("--compose", action="store_true", help="scale the docker compose deployment instead")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for the launcher (default %(default)s)")
    BusConfig.add_cli_args(parser)
    args = parser.parse_args(argv)
    if args.count < 0:
        parser.error(f"N must be >= 0, got {args.count}")
    return scale_with_compose(args.count) if args.compose else scale_local(args.count, args)


if __name__ == "__main__":
    sys.exit(main())

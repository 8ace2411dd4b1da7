"""`python -m deploy.secure --out DIR [--listen tls/0.0.0.0:7447] [--connect tls/router:7447] [--host NAME ...]
[--mounted-at /secure]`: generate the deployment CA, per-service certificates and the router/client Zenoh configs.

For the compose profile: `python -m deploy.secure --out deploy/secure/generated --connect tls/router:7447
--mounted-at /secure`, then `docker compose -f deploy/docker-compose.yml -f deploy/secure/docker-compose.secure.yml up -d`."""
from __future__ import annotations

import argparse
import sys

from deploy.secure import prepare
from deploy.secure.certs import DEFAULT_ROUTER_HOSTS


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m deploy.secure", description=__doc__)
    parser.add_argument("--out", required=True, help="directory for keys, certificates and configs (kept 0700)")
    parser.add_argument("--listen", default="tls/0.0.0.0:7447", help="router listen endpoint (default %(default)s)")
    parser.add_argument("--connect", default=None, help="endpoint clients connect to (default: the listen endpoint, "
                                                         "0.0.0.0 -> localhost)")
    parser.add_argument("--host", action="append", default=None,
                        help=f"router host name or IP for its certificate (repeatable; default {' '.join(DEFAULT_ROUTER_HOSTS)})")
    parser.add_argument("--mounted-at", default=None,
                        help="path at which the processes see --out (e.g. /secure for the compose profile)")
    args = parser.parse_args(argv)
    profile = prepare(args.out, [args.listen], tuple(args.host or DEFAULT_ROUTER_HOSTS),
                      [args.connect] if args.connect else None, args.mounted_at)
    print(f"router config: {profile.router_config}")
    print(f"client configs: {profile.directory}/client-<identity>.json5 (the planner's: client-planner.json5)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

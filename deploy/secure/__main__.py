"""`python -m deploy.secure --out DIR [--ca-dir DIR] [--listen tls/0.0.0.0:7447] [--connect tls/router:7447]
[--host NAME ...] [--mounted-at /secure]`: generate the deployment CA, per-identity certificates and the
router/client Zenoh configs.

The CA's private key is written to --ca-dir (default: the sibling `<--out>-ca/`), never into --out:
the containers mount files of --out, and whoever reads ca.key can mint a planner certificate. Keep
the CA directory off the machines that run the system; it is needed again only to issue a certificate
for an identity added later (rerunning with the same --out does that, if --ca-dir is reachable).

For the compose profile: `python -m deploy.secure --out deploy/secure/generated --connect tls/router:7447
--mounted-at /secure`, then `docker compose -f deploy/docker-compose.yml -f deploy/secure/docker-compose.secure.yml up -d`."""
from __future__ import annotations

import argparse
import sys

from deploy.secure import CertificateError, prepare
from deploy.secure.certs import DEFAULT_ROUTER_HOSTS


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m deploy.secure", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="directory for certificates, keys and configs (kept 0700)")
    parser.add_argument("--ca-dir", default=None,
                        help="directory for the CA's private key (default: the sibling <OUT>-ca; never inside --out)")
    parser.add_argument("--listen", default="tls/0.0.0.0:7447", help="router listen endpoint (default %(default)s)")
    parser.add_argument("--connect", default=None, help="endpoint clients connect to (default: the listen endpoint, "
                                                         "0.0.0.0 -> localhost)")
    parser.add_argument("--host", action="append", default=None,
                        help=f"router host name or IP for its certificate (repeatable; default {' '.join(DEFAULT_ROUTER_HOSTS)})")
    parser.add_argument("--mounted-at", default=None,
                        help="path at which the processes see --out (e.g. /secure for the compose profile)")
    args = parser.parse_args(argv)
    try:
        profile = prepare(args.out, [args.listen], tuple(args.host or DEFAULT_ROUTER_HOSTS),
                          [args.connect] if args.connect else None, args.mounted_at, ca_dir=args.ca_dir)
    except CertificateError as exc:
        print(f"python -m deploy.secure: {exc}", file=sys.stderr)
        return 1
    print(f"router config: {profile.router_config}")
    print(f"client configs: {profile.directory}/client-<identity>.json5 (the planner's: client-planner.json5, "
          f"the operator's launcher control: client-operator.json5)")
    print(f"CA key: {profile.ca_dir / 'ca.key'} (not in {profile.directory}; keep it offline)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

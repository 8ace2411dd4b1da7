"""Secure deployment profile: mutual TLS and per-identity access control on the router.

    profile = prepare(directory, listen=["tls/localhost:7447"])   # certs (once) + configs
    profile.router_config            # json5 for the router (mTLS listener, ACL)
    profile.client_config("planner") # json5 for a process with that identity (--zenoh-config)

`python -m deploy.secure --out DIR [--host NAME ...]` does the same from the shell; `gd2p up --secure`
uses it for the local system. See certs.py (identities, CA) and profile.py (TLS and ACL rules).

The CA's private key is never written into `directory` (the one whose files the processes and
containers read): it goes to `ca_dir`, by default the sibling `<directory>-ca/` (certs.ca_key_dir).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from deploy.secure.certs import (
    DEFAULT_ROUTER_HOSTS,
    IDENTITIES,
    CertificateError,
    ca_key_dir,
    generate,
    issue_missing,
)
from deploy.secure.profile import client_config, router_config, write_json5

__all__ = ["SecureProfile", "prepare", "CertificateError", "IDENTITIES"]


@dataclass(frozen=True)
class SecureProfile:
    directory: Path
    router_config: Path
    ca_dir: Path

    def client_config(self, identity: str) -> Path:
        path = self.directory / f"client-{identity}.json5"
        if not path.is_file():
            raise CertificateError(f"no client config for identity {identity!r} in {self.directory}; "
                                   f"identities: {', '.join(IDENTITIES)}")
        return path


def prepare(directory: str | os.PathLike[str], listen: list[str], router_hosts: tuple[str, ...] = DEFAULT_ROUTER_HOSTS,
            connect: list[str] | None = None, mounted_at: str | None = None,
            ca_dir: str | Path | None = None) -> SecureProfile:
    """Certificates (generated only if the directory has none yet; an identity added since is issued
    with the CA key from `ca_dir`) and fresh router/client configs. `mounted_at` is where the
    processes see the directory (e.g. "/secure" in the compose profile); `ca_dir` where the CA key is
    kept (default: the sibling `<directory>-ca/`)."""
    directory = Path(directory).resolve()
    ca_dir = Path(ca_dir).resolve() if ca_dir is not None else ca_key_dir(directory)
    if (directory / "ca.key").exists():
        raise CertificateError(
            f"{directory / 'ca.key'} must not sit in the directory the processes read (whoever reads it can mint "
            f"a planner certificate): move it out, e.g. `mkdir -m 700 {ca_dir} && mv {directory / 'ca.key'} {ca_dir}/`, "
            f"then run again")
    directory.mkdir(parents=True, exist_ok=True, mode=0o700)
    if not (directory / "ca.pem").is_file():
        generate(directory, IDENTITIES, router_hosts, ca_dir=ca_dir)
    else:
        issue_missing(directory, IDENTITIES, router_hosts, ca_dir=ca_dir)
    connect = connect or [e.replace("0.0.0.0", "localhost") for e in listen]
    router = write_json5(router_config(directory, listen, mounted_at), directory / "router.json5")
    for identity in IDENTITIES:
        write_json5(client_config(directory, identity, connect, mounted_at), directory / f"client-{identity}.json5")
    return SecureProfile(directory, router, ca_dir)

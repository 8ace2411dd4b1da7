"""Certificate authority and per-service certificates for the secure (mTLS) deployment profile.

Every process of a secure deployment authenticates to the router with its own certificate; the
certificate's common name (CN) is its identity, which the router's access-control rules match
(`cert_common_names`). `generate(out_dir)` writes

    out_dir/ca.pem                          the deployment's CA certificate (every process needs it)
    out_dir/router.pem / router.key         the router's server certificate (SAN: the router's host names)
    out_dir/<identity>.pem / <identity>.key one client certificate per identity in IDENTITIES
    ca_dir/ca.key                           the CA's private key, NOT in out_dir

The CA key goes to a separate directory (`ca_key_dir(out_dir)`: the sibling `<out_dir>-ca/` unless
given) and never into `out_dir`, the directory whose files the containers mount: whoever holds it can
mint a "planner" certificate. It is needed again only to issue a certificate for a new identity
(`issue_missing`); keep it offline otherwise.

Keys are EC P-256, certificates valid for `days` days. The CA key signs only what this script
issues, so the set of identities the ACL has to know about is exactly IDENTITIES.
"""
from __future__ import annotations

import datetime
import ipaddress
import os
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

# Identities of the processes that join the bus (deploy/secure/profile.py says what each may do).
# "planner" is the only one allowed to command the robot bridge; "cli" is the operator's everyday tools
# (push, generate, validate, sample, dataset build, status, health, e-stop), which may not command motion;
# "operator" is the only one that may reach the launcher's control key (scaling processes is host
# administration: the "cli" certificate is handed to every push or dataset client, this one is not).
# "tracker" is a user's object tracker beside real hardware: it may publish only the object track.
IDENTITIES: tuple[str, ...] = ("planner", "robot_bridge", "generator", "validator", "sampler", "recorder",
                               "launcher", "cli", "operator", "tracker")
ROUTER_IDENTITY = "router"
DEFAULT_ROUTER_HOSTS: tuple[str, ...] = ("localhost", "127.0.0.1", "router")


class CertificateError(RuntimeError):
    """The certificate set could not be generated or is incomplete."""


@dataclass(frozen=True)
class Credentials:
    """Paths of one identity's certificate and private key, and of the CA that signed it."""

    identity: str
    certificate: Path
    private_key: Path
    ca_certificate: Path


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "GD2P"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _san(hosts: tuple[str, ...]) -> x509.SubjectAlternativeName:
    names: list[x509.GeneralName] = []
    for host in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return x509.SubjectAlternativeName(names)


def _write(path: Path, data: bytes, private: bool = False) -> None:
    path.write_bytes(data)
    if private:
        os.chmod(path, 0o600)


def _pem_key(key: ec.EllipticCurvePrivateKey) -> bytes:
    # PKCS#8: the format rustls (zenoh's TLS) reads for EC keys.
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _issue(common_name: str, key: ec.EllipticCurvePrivateKey, ca_cert: x509.Certificate,
           ca_key: ec.EllipticCurvePrivateKey, days: int, server_hosts: tuple[str, ...] | None) -> x509.Certificate:
    now = datetime.datetime.now(datetime.timezone.utc)
    builder = (x509.CertificateBuilder()
               .subject_name(_name(common_name)).issuer_name(ca_cert.subject)
               .public_key(key.public_key()).serial_number(x509.random_serial_number())
               .not_valid_before(now - datetime.timedelta(minutes=5))
               .not_valid_after(now + datetime.timedelta(days=days))
               .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
               .add_extension(x509.KeyUsage(digital_signature=True, key_encipherment=False, content_commitment=False,
                                            data_encipherment=False, key_agreement=True, key_cert_sign=False,
                                            crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
               .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False))
    if server_hosts is not None:
        builder = (builder.add_extension(_san(server_hosts), critical=False)
                   .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False))
    else:
        # Clients carry their CN as a DNS SAN too: rustls validates names from SANs only.
        builder = (builder.add_extension(_san((common_name,)), critical=False)
                   .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False))
    return builder.sign(ca_key, hashes.SHA256())


def _make_ca(days: int) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    key = _key()
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder()
            .subject_name(_name("GD2P deployment CA")).issuer_name(_name("GD2P deployment CA"))
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, key_encipherment=False, content_commitment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    return cert, key


def ca_key_dir(out_dir: str | Path) -> Path:
    """Where the CA key of the certificates in `out_dir` is kept by default: the sibling `<out_dir>-ca/`."""
    out = Path(out_dir).resolve()
    return out.with_name(out.name + "-ca")


def _check_ca_dir(out: Path, ca_dir: Path) -> None:
    out, ca_dir = out.resolve(), ca_dir.resolve()
    if ca_dir == out or out in ca_dir.parents:
        raise CertificateError(f"the CA key must not be kept in {out} (the directory the processes mount); "
                               f"choose a CA directory outside it, e.g. {ca_key_dir(out)}")


def _load_ca(out: Path, ca_dir: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    cert = x509.load_pem_x509_certificate((out / "ca.pem").read_bytes())
    key_path = ca_dir / "ca.key"
    if not key_path.is_file():
        raise CertificateError(f"the CA key {key_path} is not here: put it back (from where it is kept offline) "
                               f"to issue new certificates, or generate a fresh set in a new directory")
    key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey) or key.public_key() != cert.public_key():
        raise CertificateError(f"{key_path} is not the key of the CA certificate {out / 'ca.pem'}")
    return cert, key


def _issue_into(out: Path, identities: tuple[str, ...], ca_cert: x509.Certificate, ca_key: ec.EllipticCurvePrivateKey,
                router_hosts: tuple[str, ...], days: int) -> dict[str, Credentials]:
    issued: dict[str, Credentials] = {}
    for identity in identities:
        key = _key()
        hosts = tuple(router_hosts) if identity == ROUTER_IDENTITY else None
        cert = _issue(identity, key, ca_cert, ca_key, days, hosts)
        cert_path, key_path = out / f"{identity}.pem", out / f"{identity}.key"
        _write(cert_path, cert.public_bytes(serialization.Encoding.PEM))
        _write(key_path, _pem_key(key), private=True)
        issued[identity] = Credentials(identity, cert_path, key_path, out / "ca.pem")
    return issued


def generate(out_dir: str | Path, identities: tuple[str, ...] = IDENTITIES,
             router_hosts: tuple[str, ...] = DEFAULT_ROUTER_HOSTS, days: int = 365,
             ca_dir: str | Path | None = None) -> dict[str, Credentials]:
    """Write a fresh CA, the router's certificate and one client certificate per identity into `out_dir`,
    and the CA's private key into `ca_dir` (default `ca_key_dir(out_dir)`; never inside `out_dir`).

    Returns identity -> Credentials (the router's under ROUTER_IDENTITY).
    """
    if ROUTER_IDENTITY in identities:
        raise CertificateError(f"{ROUTER_IDENTITY!r} is reserved for the router's own certificate")
    out = Path(out_dir)
    ca_dir = Path(ca_dir) if ca_dir is not None else ca_key_dir(out)
    _check_ca_dir(out, ca_dir)
    if (ca_dir / "ca.key").exists():
        raise CertificateError(f"{ca_dir / 'ca.key'} exists already: it is the key of another certificate set; "
                               f"choose another output or CA directory rather than overwrite it")
    out.mkdir(parents=True, exist_ok=True)
    ca_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
    os.chmod(ca_dir, 0o700)
    ca_cert, ca_key = _make_ca(days)
    _write(ca_dir / "ca.key", _pem_key(ca_key), private=True)
    _write(out / "ca.pem", ca_cert.public_bytes(serialization.Encoding.PEM))
    return _issue_into(out, (ROUTER_IDENTITY, *identities), ca_cert, ca_key, router_hosts, days)


def missing_identities(out_dir: str | Path, identities: tuple[str, ...] = IDENTITIES) -> tuple[str, ...]:
    """The identities (and the router) without a certificate or key in `out_dir`."""
    out = Path(out_dir)
    return tuple(i for i in (ROUTER_IDENTITY, *identities)
                 if not (out / f"{i}.pem").is_file() or not (out / f"{i}.key").is_file())


def issue_missing(out_dir: str | Path, identities: tuple[str, ...] = IDENTITIES,
                  router_hosts: tuple[str, ...] = DEFAULT_ROUTER_HOSTS, days: int = 365,
                  ca_dir: str | Path | None = None) -> dict[str, Credentials]:
    """Issue certificates for the identities `out_dir` has none for yet (e.g. one added to IDENTITIES
    since it was generated), signed by its CA; needs the CA key in `ca_dir`. Returns what it issued."""
    out = Path(out_dir)
    missing = missing_identities(out, identities)
    if not missing:
        return {}
    ca_dir = Path(ca_dir) if ca_dir is not None else ca_key_dir(out)
    _check_ca_dir(out, ca_dir)
    ca_cert, ca_key = _load_ca(out, ca_dir)
    return _issue_into(out, missing, ca_cert, ca_key, router_hosts, days)


def credentials(cert_dir: str | Path, identity: str) -> Credentials:
    """The already generated credentials of `identity` in `cert_dir` (CertificateError if missing)."""
    base = Path(cert_dir)
    creds = Credentials(identity, base / f"{identity}.pem", base / f"{identity}.key", base / "ca.pem")
    missing = [str(p) for p in (creds.certificate, creds.private_key, creds.ca_certificate) if not p.is_file()]
    if missing:
        raise CertificateError(f"no credentials for {identity!r} in {base}: missing {', '.join(missing)} "
                               f"(run `python -m deploy.secure --out {base}`)")
    return creds

"""TLS material for the stack: a private CA, the router's server certificate and one client certificate per
identity (for mTLS; the client certificate's common name is the identity), and the checks a launch runs on them.

EC P-256 keys, PEM files; private keys are written mode 600. The CA's key is written too (to issue more
certificates later); it does not belong on the robot (see deploy/zenoh/README.md).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

ROUTER_CERT_NAME = "gpmppi-router"  # the router certificate's common name
VALID_DAYS = 825  # the longest lifetime common TLS clients accept for a leaf certificate


def _name(common_name: str) -> x509.Name:
    return x509.Name(
        [x509.NameAttribute(NameOID.ORGANIZATION_NAME, "gpmppi"), x509.NameAttribute(NameOID.COMMON_NAME, common_name)]
    )


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _write(path: Path, data: bytes, private: bool) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _sans(hosts: list[str]) -> list[x509.GeneralName]:
    names: list[x509.GeneralName] = []
    for host in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return names


def make_tls(directory: Path, identities: list[str], hosts: list[str]) -> dict[str, tuple[Path, Path]]:
    """Write ca, router and one client certificate per identity; {name: (certificate, key)}. `hosts` are the
    names and addresses the router is reached at (checked by clients against the router's certificate)."""
    directory.mkdir(parents=True, exist_ok=True)
    os.chmod(directory, 0o700)
    now = dt.datetime.now(dt.timezone.utc)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = _name("gpmppi CA")
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=VALID_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .sign(ca_key, hashes.SHA256())
    )
    out: dict[str, tuple[Path, Path]] = {}

    def save(name: str, cert: x509.Certificate, key: ec.EllipticCurvePrivateKey) -> None:
        cert_path, key_path = directory / f"{name}.pem", directory / f"{name}.key"
        _write(cert_path, cert.public_bytes(serialization.Encoding.PEM), private=False)
        _write(key_path, _key_pem(key), private=True)
        out[name] = (cert_path, key_path)

    save("ca", ca, ca_key)

    def leaf(common_name: str, server: bool) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
        key = ec.generate_private_key(ec.SECP256R1())
        builder = (
            x509.CertificateBuilder()
            .subject_name(_name(common_name))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=VALID_DAYS))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH]),
                critical=False,
            )
        )
        if server:
            builder = builder.add_extension(x509.SubjectAlternativeName(_sans(hosts)), critical=False)
        return builder.sign(ca_key, hashes.SHA256()), key

    save("router", *leaf(ROUTER_CERT_NAME, server=True))
    for identity in identities:
        save(identity, *leaf(identity, server=False))
    return out


def check_pair(cert_path: Path, key_path: Path, ca_path: Path | None, where: str) -> x509.Certificate:
    """The certificate at cert_path, after checking it parses, matches the key at key_path, is within its
    validity and (if ca_path) is signed by that CA. Raises ValueError naming `where` (file and fields)."""
    for path in (cert_path, key_path):
        if not path.is_file():
            raise ValueError(f"{where}: {path} does not exist")
    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    except ValueError as exc:
        raise ValueError(f"{where}: {cert_path} is not a PEM certificate ({exc})") from None
    try:
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{where}: {key_path} is not an unencrypted PEM private key ({exc})") from None
    raw = serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    if cert.public_key().public_bytes(*raw) != key.public_key().public_bytes(*raw):
        raise ValueError(
            f"{where}: the certificate {cert_path} does not match the private key {key_path} "
            "(they are from different pairs); re-issue them with `gpmppi secure init --tls`"
        )
    now = dt.datetime.now(dt.timezone.utc)
    if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
        raise ValueError(
            f"{where}: {cert_path} is valid {cert.not_valid_before_utc:%Y-%m-%d} to "
            f"{cert.not_valid_after_utc:%Y-%m-%d}, not now; issue a new one"
        )
    if ca_path is not None:
        if not ca_path.is_file():
            raise ValueError(f"{where}: root_ca_certificate {ca_path} does not exist")
        ca = x509.load_pem_x509_certificate(ca_path.read_bytes())
        try:
            cert.verify_directly_issued_by(ca)
        except (ValueError, TypeError, InvalidSignature):
            raise ValueError(f"{where}: {cert_path} is not signed by the root_ca_certificate {ca_path}") from None
    return cert

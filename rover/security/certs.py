"""Certificates for mutual TLS between the hosts of a pipeline: issuing them, and reading them back.

One certificate authority per deployment signs one certificate per host (and one for the read-only
`monitor` identity). A certificate's common name is its identity in the access-control rules
(`rover.security.acl`); its subject alternative names are the addresses the others reach it at.
The CA's private key is never written: adding a host or revoking a stolen certificate means a new
CA and new certificates for every host (docs/security.md).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from rover.errors import BadInput
from rover.pipeline.validation import is_ip

MONITOR = "monitor"
"""The identity of `rover status` and viewers: reads host status, nothing else."""
CA_DAYS = 1825
"""The CA's lifetime: five years; a compromise is answered with a new CA anyway."""
HOST_DAYS = 365
"""A host certificate's lifetime: a year, so a forgotten copy stops working on its own."""
BACKDATE = dt.timedelta(minutes=5)
"""Certificates are valid from a little before now: clocks of the hosts differ by seconds to minutes."""


@dataclass(frozen=True)
class CertInfo:
    """What the checks need from a certificate."""

    path: str
    common_name: str
    names: tuple[str, ...]
    """subject alternative names: DNS names and IP addresses, as text"""
    not_before: dt.datetime
    not_after: dt.datetime
    cert: x509.Certificate

    def covers(self, address: str) -> bool:
        """Whether `address` (an IP or a DNS name) is one of the certificate's names, as TLS checks it."""
        try:
            ip = ipaddress.ip_address(address.strip("[]"))
        except ValueError:
            return any(_dns_match(name, address) for name in self.names if not is_ip(name))
        return any(is_ip(name) and ipaddress.ip_address(name) == ip for name in self.names)

    def described_names(self) -> str:
        return ", ".join(f"{'IP' if is_ip(n) else 'DNS'}:{n}" for n in self.names) or "none"


def _dns_match(pattern: str, name: str) -> bool:
    pattern, name = pattern.lower().rstrip("."), name.lower().rstrip(".")
    if pattern.startswith("*."):
        head, _, rest = name.partition(".")
        return bool(head) and rest == pattern[2:]
    return pattern == name


def read_cert(path: str | Path) -> CertInfo:
    """A PEM certificate's identity, names and validity; BadInput naming the file when it is not one."""
    data = _read(path)
    try:
        cert = x509.load_pem_x509_certificate(data)
    except ValueError:
        raise BadInput(f"{path}: not a PEM certificate") from None
    cns = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    try:
        sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        names = tuple(sans.get_values_for_type(x509.DNSName)) + tuple(
            str(ip) for ip in sans.get_values_for_type(x509.IPAddress)
        )
    except x509.ExtensionNotFound:
        names = ()
    return CertInfo(
        str(path),
        str(cns[0].value) if cns else "",
        names,
        cert.not_valid_before_utc,
        cert.not_valid_after_utc,
        cert,
    )


def read_private_key(path: str | Path) -> ec.EllipticCurvePrivateKey | object:
    """A PEM private key (unencrypted: the hosts start unattended); BadInput naming the file otherwise."""
    data = _read(path)
    try:
        return serialization.load_pem_private_key(data, password=None)
    except TypeError:
        raise BadInput(f"{path}: the private key is encrypted; Rover needs it unencrypted (mode 0600)") from None
    except ValueError:
        raise BadInput(f"{path}: not a PEM private key") from None


def _read(path: str | Path) -> bytes:
    try:
        with open(path, "rb") as stream:
            return stream.read(1 << 20)
    except FileNotFoundError:
        raise BadInput(f"{path}: no such file") from None
    except OSError as exc:
        raise BadInput(f"{path}: cannot read: {exc.strerror or exc}") from None


def signed_by(cert: CertInfo, ca: CertInfo) -> bool:
    """Whether the CA's key signed `cert` (the chain TLS checks, one level deep)."""
    try:
        cert.cert.verify_directly_issued_by(ca.cert)
        return True
    except (ValueError, TypeError, InvalidSignature):
        return False


def key_matches(cert: CertInfo, key: object) -> bool:
    public = getattr(key, "public_key", None)
    if public is None:
        return False
    fmt = (serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
    return bool(public().public_bytes(*fmt) == cert.cert.public_key().public_bytes(*fmt))


# -- issuing


@dataclass(frozen=True)
class Issued:
    """The files `issue` wrote."""

    ca: Path
    identities: dict[str, tuple[Path, Path]]
    """name -> (certificate, private key)"""


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _alt_names(names: Iterable[str]) -> list[x509.GeneralName]:
    out: list[x509.GeneralName] = []
    for name in dict.fromkeys(names):
        if is_ip(name.strip("[]")):
            out.append(x509.IPAddress(ipaddress.ip_address(name.strip("[]"))))
        else:
            out.append(x509.DNSName(name))
    return out


def issue(
    out_dir: str | Path,
    names: Mapping[str, list[str]],
    *,
    monitor: bool = False,
    label: str = "rover",
    days: int = HOST_DAYS,
    force: bool = False,
    now: dt.datetime | None = None,
) -> Issued:
    """Write a new CA certificate and one certificate and key per host of `names` (host -> the DNS
    names and IPs it is reached at) into `out_dir`, plus the monitor's when asked. Nothing is
    written when a file would be replaced without `force`."""
    out = Path(out_dir)
    idents = list(names) + ([MONITOR] if monitor else [])
    files = [out / "ca.pem"] + [out / f"{n}.{ext}" for n in idents for ext in ("pem", "key")]
    existing = [str(f) for f in files if f.exists()]
    if existing and not force:
        raise BadInput(f"{existing[0]}: already exists (pass --force to replace it and the other files of this set)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BadInput(f"{out}: cannot create the folder: {exc.strerror or exc}") from None
    start = (now or dt.datetime.now(dt.UTC)) - BACKDATE
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = _name(f"{label} CA")
    ca_cert = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(start + dt.timedelta(days=CA_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(False, False, False, False, False, True, True, False, False),  # cert and CRL signing
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    written: dict[str, tuple[Path, Path]] = {}
    for ident in idents:
        key = ec.generate_private_key(ec.SECP256R1())
        usages = [ExtendedKeyUsageOID.CLIENT_AUTH] + ([] if ident == MONITOR else [ExtendedKeyUsageOID.SERVER_AUTH])
        alt = _alt_names([ident] + list(names.get(ident, [])))
        cert = (
            x509.CertificateBuilder()
            .subject_name(_name(ident))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(start)
            .not_valid_after(start + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(True, False, False, False, False, False, False, False, False), critical=True)
            .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
            .add_extension(x509.SubjectAlternativeName(alt), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        written[ident] = (out / f"{ident}.pem", out / f"{ident}.key")
        _write(
            written[ident][1],
            key.private_bytes(
                serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
            ),
            0o600,
        )
        _write(written[ident][0], cert.public_bytes(serialization.Encoding.PEM), 0o644)
    _write(out / "ca.pem", ca_cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return Issued(out / "ca.pem", written)


def _write(path: Path, data: bytes, mode: int) -> None:
    """Write a file with `mode` from its creation (a key is never readable by others, not even briefly)."""
    tmp = path.with_name(f".{path.name}.partial")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
        with os.fdopen(fd, "wb") as stream:
            os.fchmod(stream.fileno(), mode)
            stream.write(data)
        os.replace(tmp, path)
    except OSError as exc:
        raise BadInput(f"{path}: cannot write: {exc.strerror or exc}") from None

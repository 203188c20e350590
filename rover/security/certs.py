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
import re
import stat
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
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
MAX_COMMON_NAME = 64
"""X.509's upper bound on a common name (characters)."""
DNS_NAME_RE = re.compile(
    r"^(?=.{1,253}$)(\*\.)?[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$"
)
"""A DNS name a certificate can carry (ASCII letters, digits and hyphens per label; a leading `*.`)."""
BACKDATE = dt.timedelta(minutes=5)
"""Certificates are valid from a little before now: clocks of the hosts differ by seconds to minutes."""


@dataclass(frozen=True)
class CertInfo:
    """What the checks need from a certificate."""

    path: str
    common_name: str
    dns_names: tuple[str, ...]
    ip_names: tuple[str, ...]
    """subject alternative names of each kind: TLS matches an IP only against IP names"""
    not_before: dt.datetime
    not_after: dt.datetime
    cert: x509.Certificate

    @property
    def names(self) -> tuple[str, ...]:
        return self.dns_names + self.ip_names

    def covers(self, address: str) -> bool:
        """Whether `address` (an IP or a DNS name) is one of the certificate's names, as TLS checks it."""
        try:
            ip = ipaddress.ip_address(address.strip("[]"))
        except ValueError:
            return any(_dns_match(name, address) for name in self.dns_names)
        return any(ipaddress.ip_address(name) == ip for name in self.ip_names)

    def described_names(self) -> str:
        shown = [f"DNS:{n}" for n in self.dns_names] + [f"IP:{n}" for n in self.ip_names]
        return ", ".join(shown) or "none"


def _dns_match(pattern: str, name: str) -> bool:
    """As webpki matches: case-insensitive, the dialled name may be absolute (`nuc.lab.`) but the
    certificate's may not, a wildcard only as the whole first label of a name of at least three
    labels, standing for exactly one label."""
    if pattern.endswith("."):
        return False
    pattern, name = pattern.lower(), name.lower().removesuffix(".")
    if pattern.startswith("*."):
        if pattern.count(".") < 2:
            return False
        head, _, rest = name.partition(".")
        return bool(head) and rest == pattern[2:]
    return pattern == name


def read_cert(path: str | Path) -> CertInfo:
    """A PEM certificate's identity, names and validity; BadInput naming the file when it is not one."""
    data = _read(path)
    count = data.count(b"-----BEGIN CERTIFICATE-----")
    if count > 1:
        raise BadInput(
            f"{path}: holds {count} certificates; TLS would trust every one: give one certificate (one CA) per file"
        )
    try:
        cert = x509.load_pem_x509_certificate(data)
        cns = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
        try:
            sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
            dns = tuple(sans.get_values_for_type(x509.DNSName))
            ips = tuple(str(ip) for ip in sans.get_values_for_type(x509.IPAddress))
        except x509.ExtensionNotFound:
            dns, ips = (), ()
        return CertInfo(
            str(path),
            str(cns[0].value) if cns else "",
            dns,
            ips,
            cert.not_valid_before_utc,
            cert.not_valid_after_utc,
            cert,
        )
    except ValueError:
        raise BadInput(f"{path}: not a PEM certificate") from None
    except UnsupportedAlgorithm as exc:
        raise BadInput(f"{path}: a certificate of an algorithm Rover cannot read ({exc})") from None


def read_private_key(path: str | Path) -> ec.EllipticCurvePrivateKey | object:
    """A PEM private key (unencrypted: the hosts start unattended); BadInput naming the file otherwise."""
    data = _read(path)
    try:
        return serialization.load_pem_private_key(data, password=None)
    except TypeError:
        raise BadInput(f"{path}: the private key is encrypted; Rover needs it unencrypted (mode 0600)") from None
    except ValueError:
        raise BadInput(f"{path}: not a PEM private key") from None
    except UnsupportedAlgorithm as exc:
        raise BadInput(f"{path}: a private key of an algorithm Rover cannot read ({exc})") from None


def _read(path: str | Path) -> bytes:
    """At most 1 MiB of a regular file (not a FIFO, device or folder, which would hang or mislead)."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise BadInput(f"{path}: not a regular file")
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
    written when a file would be replaced without `force`, or when a name or lifetime is invalid."""
    for ident, given in names.items():
        if len(ident) > MAX_COMMON_NAME:
            raise BadInput(f"host name {ident!r} is longer than a certificate name may be ({MAX_COMMON_NAME})")
        for name in given:
            if not (is_ip(name.strip("[]")) or DNS_NAME_RE.match(name)):
                raise BadInput(f"{ident}={name}: not an IP address or an ASCII DNS name (letters, digits, - and .)")
    if not 1 <= days <= CA_DAYS:
        raise BadInput(f"a host certificate lasts 1 to {CA_DAYS} days (the CA's lifetime), not {days}")
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
    ca_name = _name(f"{label} CA"[-MAX_COMMON_NAME:])
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
        own = [ident] if DNS_NAME_RE.match(ident) else []  # `base_2` is a host name but no DNS name
        alt = _alt_names(own + list(names.get(ident, [])))
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
        if os.path.lexists(tmp):
            os.unlink(tmp)  # a leftover, or a planted link: never write through it
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, mode)
        with os.fdopen(fd, "wb") as stream:
            os.fchmod(stream.fileno(), mode)
            stream.write(data)
        os.replace(tmp, path)
    except OSError as exc:
        raise BadInput(f"{path}: cannot write: {exc.strerror or exc}") from None

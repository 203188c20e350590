"""The checks made before anything starts under `security:`: every file there and readable, every
certificate signed by the CA, current, naming its host and covering the addresses it serves, every
key belonging to its certificate. Each problem is one diagnostic naming the file and its line in
the pipeline."""

from __future__ import annotations

import datetime as dt
import os
import stat
from collections.abc import Collection

from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID

from rover.errors import BadInput, Diagnostic
from rover.pipeline.spec import MONITOR, Identity, PipelineSpec
from rover.pipeline.validation import served_addresses
from rover.security.certs import CertInfo, key_matches, read_cert, read_private_key, signed_by

EXPIRY_WARNING = dt.timedelta(days=30)
"""A certificate this close to its end is reported by every check: time to issue new ones."""


def _when(moment: dt.datetime) -> str:
    return moment.strftime("%Y-%m-%d %H:%M UTC")


def _validity(info: CertInfo, what: str, now: dt.datetime) -> str | None:
    if now > info.not_after:
        return f"{info.path}: {what} expired on {_when(info.not_after)}"
    if now < info.not_before:
        return f"{info.path}: {what} is not valid before {_when(info.not_before)} (is this clock right?)"
    return None


def _expires_soon(info: CertInfo, what: str, now: dt.datetime) -> str | None:
    if info.not_after - now >= EXPIRY_WARNING:
        return None
    return f"{info.path}: warning: {what} expires in {(info.not_after - now).days} days ({_when(info.not_after)})"


def _usage_problems(info: CertInfo, what: str, *, needs_server: bool) -> list[str]:
    """What TLS would refuse in a leaf certificate's extensions: a CA certificate used as a host's,
    or extended key usages without client (or, for a listening host, server) authentication."""
    found = []
    try:
        if info.cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca:
            found.append(f"{info.path}: {what} is a CA certificate, not a host's")
    except x509.ExtensionNotFound:
        pass
    try:
        usages = set(info.cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)
    except x509.ExtensionNotFound:
        return found
    wanted = {ExtendedKeyUsageOID.CLIENT_AUTH: "client"} | (
        {ExtendedKeyUsageOID.SERVER_AUTH: "server"} if needs_server else {}
    )
    missing = [word for oid, word in wanted.items() if oid not in usages]
    if missing:
        found.append(f"{info.path}: {what} is not for TLS {' and '.join(missing)} authentication (extended key usage)")
    return found


def check_security(
    spec: PipelineSpec,
    hosts: Collection[str] | None = None,
    *,
    monitor: bool = False,
    now: dt.datetime | None = None,
) -> tuple[list[Diagnostic], list[str]]:
    """Problems (and warnings) with the CA, the identities of `hosts` (default: every host) and,
    when asked, the monitor's. Nothing to check without `security:`."""
    security = spec.security
    if security is None:
        return [], []
    now = now or dt.datetime.now(dt.UTC)
    doc = spec.doc
    problems: list[Diagnostic] = []
    warnings: list[str] = []
    try:
        ca: CertInfo | None = read_cert(security.ca)
    except BadInput as exc:
        problems.append(doc.diag(("security", "ca"), str(exc)))
        ca = None
    if ca is not None and (problem := _validity(ca, "the CA certificate", now)):
        problems.append(doc.diag(("security", "ca"), problem))
    elif ca is not None and (soon := _expires_soon(ca, "the CA certificate", now)):
        warnings.append(soon)

    def identity(name: str, ident: Identity, path: tuple[str, ...]) -> None:
        what = f"the certificate of {'the monitor' if name == MONITOR else f'host {name}'}"
        try:
            info = read_cert(ident.cert)
        except BadInput as exc:
            problems.append(doc.diag(path + ("cert",), str(exc)))
            info = None
        try:
            key = read_private_key(ident.key)
        except BadInput as exc:
            problems.append(doc.diag(path + ("key",), str(exc)))
            key = None
        else:
            mode = stat.S_IMODE(os.stat(ident.key).st_mode)
            if mode & 0o077:
                warnings.append(f"{ident.key}: warning: private key readable by others (mode {mode:04o}); chmod 600")
        if info is None:
            return
        found: list[str] = []
        if info.common_name != name:
            found.append(
                f"{info.path}: {what} is for {info.common_name or 'no name'!r}, not {name!r} (its common name)"
            )
        if problem := _validity(info, what, now):
            found.append(problem)
        elif soon := _expires_soon(info, what, now):
            warnings.append(soon)
        found += _usage_problems(info, what, needs_server=name != MONITOR and bool(spec.hosts[name].listen))
        if ca is not None and not signed_by(info, ca):
            found.append(f"{info.path}: {what} is not signed by the CA in {ca.path}")
        if key is not None and not key_matches(info, key):
            problems.append(doc.diag(path + ("key",), f"{ident.key}: this private key does not belong to {info.path}"))
        if name != MONITOR:
            uncovered: dict[str, list[str]] = {}
            for address, why in served_addresses(spec, name):
                if not info.covers(address):
                    uncovered.setdefault(address, []).append(why)
            for address, whys in uncovered.items():
                found.append(
                    f"{info.path}: {what} does not cover {address} ({'; '.join(whys)}); "
                    f"its names: {info.described_names()}"
                )
        problems.extend(doc.diag(path + ("cert",), text) for text in found)

    for name in spec.hosts if hosts is None else hosts:
        if name in security.hosts:
            identity(name, security.hosts[name], ("security", "hosts", name))
    if monitor:
        if security.monitor is None:
            problems.append(doc.diag(("security",), "security: has no monitor: identity (rover certs --monitor)"))
        else:
            identity(MONITOR, security.monitor, ("security", "monitor"))
    return problems, warnings

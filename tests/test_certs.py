"""Issuing and reading the certificates of `security:`: one CA, one certificate and key per host
(plus the read-only monitor), checked with real cryptography and, when present, with openssl."""

from __future__ import annotations

import datetime as dt
import os
import re
import shutil
import stat
import subprocess
from pathlib import Path

import pytest
import yaml
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
from helpers import run_rover
from netns import security_block

from rover.errors import BadInput
from rover.security.certs import (
    BACKDATE,
    CA_DAYS,
    MONITOR,
    issue,
    key_matches,
    read_cert,
    read_private_key,
    signed_by,
)

NAMES = {"nuc": ["10.0.0.1", "nuc.lab", "fd00::1"], "base": ["[fd00::2]", "Base.Lab"], "laptop": []}
NOW = dt.datetime(2030, 6, 1, 12, 0, tzinfo=dt.UTC)


@pytest.fixture(scope="module")
def issued(tmp_path_factory):
    """One set for the whole module (host certificates of 30 days, issued at NOW, with the monitor)."""
    return issue(tmp_path_factory.mktemp("certs"), NAMES, monitor=True, days=30, now=NOW)


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def eku(path) -> set:
    cert = read_cert(path).cert
    return set(cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)


def test_issue_writes_the_ca_and_a_certificate_and_key_per_identity(issued):
    """Files: ca.pem plus <name>.pem/<name>.key for every host and the monitor, nothing else."""
    out = issued.ca.parent
    assert issued.ca == out / "ca.pem"
    assert list(issued.identities) == ["nuc", "base", "laptop", MONITOR]
    for name, (cert, key) in issued.identities.items():
        assert (cert, key) == (out / f"{name}.pem", out / f"{name}.key")
    expected = {"ca.pem"} | {f"{n}.{ext}" for n in issued.identities for ext in ("pem", "key")}
    assert {p.name for p in out.iterdir()} == expected


def test_common_name_is_the_host_and_names_are_the_host_plus_the_given_ones(issued):
    """CN = identity; SANs = the identity as a DNS name plus the given IPs (v4 and v6, brackets
    dropped) and DNS names."""
    nuc = read_cert(issued.identities["nuc"][0])
    assert nuc.common_name == "nuc"
    assert sorted(nuc.names) == sorted(["nuc", "nuc.lab", "10.0.0.1", "fd00::1"])
    sans = nuc.cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert sorted(sans.get_values_for_type(x509.DNSName)) == ["nuc", "nuc.lab"]
    assert sorted(str(ip) for ip in sans.get_values_for_type(x509.IPAddress)) == ["10.0.0.1", "fd00::1"]
    base = read_cert(issued.identities["base"][0])
    assert base.common_name == "base"
    assert sorted(base.names) == sorted(["base", "Base.Lab", "fd00::2"])
    laptop = read_cert(issued.identities["laptop"][0])
    assert (laptop.common_name, laptop.names) == ("laptop", ("laptop",))
    monitor = read_cert(issued.identities[MONITOR][0])
    assert (monitor.common_name, monitor.names) == (MONITOR, (MONITOR,))
    assert "nuc" not in read_cert(issued.ca).common_name


def test_covers_matches_ips_exactly_and_dns_names_case_insensitively(issued):
    """IPs compare as addresses (any spelling, brackets allowed), never as text or against DNS
    names; DNS names ignore case and a trailing dot; anything else is refused."""
    nuc = read_cert(issued.identities["nuc"][0])
    for address in ("10.0.0.1", "fd00::1", "[fd00::1]", "fd00:0:0:0:0:0:0:1", "nuc.lab", "NUC.Lab", "nuc.lab.", "nuc"):
        assert nuc.covers(address), address
    for address in ("10.0.0.2", "10.0.0.10", "::ffff:10.0.0.1", "fd00::2", "lab", "x.nuc.lab", "nuc.la", "base"):
        assert not nuc.covers(address), address
    base = read_cert(issued.identities["base"][0])
    assert base.covers("base.lab") and base.covers("[fd00::2]")
    assert not base.covers("fd00::1")
    assert nuc.described_names().split(", ") == ["DNS:nuc", "DNS:nuc.lab", "IP:10.0.0.1", "IP:fd00::1"]


def test_wildcard_names_cover_exactly_one_label(tmp_path):
    """`*.robot.lab` covers nuc.robot.lab (any case) but neither robot.lab itself, a.b.robot.lab,
    .robot.lab nor an IP; `*.lab` (a wildcard over two labels, which webpki refuses) covers nothing."""
    issued = issue(tmp_path, {"nuc": ["*.robot.lab"], "base": ["*.lab"]})
    nuc = read_cert(issued.identities["nuc"][0])
    assert nuc.covers("nuc.robot.lab") and nuc.covers("Other.ROBOT.lab")
    for address in ("robot.lab", "a.b.robot.lab", ".robot.lab", "nuc.robot.lab.org", "nuc.robot.lan", "10.0.0.1"):
        assert not nuc.covers(address), address
    base = read_cert(issued.identities["base"][0])
    assert not base.covers("nuc.lab") and not base.covers("lab")


def test_each_certificate_is_signed_by_its_ca_and_by_no_other(issued, tmp_path):
    """signed_by holds for the set's own CA (same label or not) and fails for a second issue()'s CA,
    and for a host certificate taken as a CA."""
    ca = read_cert(issued.ca)
    other = issue(tmp_path, {"nuc": ["10.0.0.1"]}, now=NOW)
    other_ca = read_cert(other.ca)
    assert other_ca.common_name == ca.common_name == "rover CA"  # same name: only the signature tells them apart
    for cert, _key in issued.identities.values():
        info = read_cert(cert)
        assert signed_by(info, ca)
        assert not signed_by(info, other_ca)
        assert not signed_by(info, read_cert(issued.identities["base"][0]))
    assert signed_by(read_cert(other.identities["nuc"][0]), other_ca)
    assert not signed_by(read_cert(other.identities["nuc"][0]), ca)
    assert signed_by(ca, ca)  # self-signed


def test_keys_are_mode_0600_and_certificates_0644(issued):
    """Private keys are readable by their owner only; certificates and the CA by anyone."""
    for cert, key in issued.identities.values():
        assert mode(key) == 0o600, key
        assert mode(cert) == 0o644, cert
    assert mode(issued.ca) == 0o644


def test_modes_do_not_depend_on_the_umask(tmp_path):
    """Under umask 077 certificates are still 0644, under umask 0 keys still 0600; no partial file is left."""
    previous = os.umask(0o077)
    try:
        strict = issue(tmp_path / "strict", {"nuc": []})
        os.umask(0)
        loose = issue(tmp_path / "loose", {"nuc": []})
    finally:
        os.umask(previous)
    assert [mode(strict.ca), mode(strict.identities["nuc"][0])] == [0o644, 0o644]
    assert mode(loose.identities["nuc"][1]) == 0o600
    assert sorted(p.name for p in (tmp_path / "loose").iterdir()) == ["ca.pem", "nuc.key", "nuc.pem"]


def test_key_matches_pairs_each_key_with_its_own_certificate_only(issued):
    """Every identity's key matches its certificate and no other identity's."""
    for name, (cert, _key) in issued.identities.items():
        info = read_cert(cert)
        for other, (_cert, key) in issued.identities.items():
            assert key_matches(info, read_private_key(key)) == (name == other), (name, other)
    assert not key_matches(read_cert(issued.identities["nuc"][0]), object())


def test_hosts_are_servers_and_clients_the_monitor_only_a_client(issued):
    """Extended key usage: serverAuth and clientAuth for hosts (they listen and connect), clientAuth
    alone for the monitor (it can never pose as a host); host certs are not CAs, the CA is one."""
    both = {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH}
    for name in ("nuc", "base", "laptop"):
        assert eku(issued.identities[name][0]) == both, name
    assert eku(issued.identities[MONITOR][0]) == {ExtendedKeyUsageOID.CLIENT_AUTH}
    ca = read_cert(issued.ca).cert
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    host = read_cert(issued.identities["nuc"][0]).cert
    assert not host.extensions.get_extension_for_class(x509.BasicConstraints).value.ca


def test_lifetimes_ca_five_years_hosts_the_given_days(issued):
    """Everything is valid from 5 minutes before `now`; the CA for 1825 days, the identities for `days`."""
    ca = read_cert(issued.ca)
    assert ca.not_before == NOW - BACKDATE
    assert ca.not_after - ca.not_before == dt.timedelta(days=CA_DAYS) == dt.timedelta(days=1825)
    for cert, _key in issued.identities.values():
        info = read_cert(cert)
        assert info.not_before == NOW - BACKDATE
        assert info.not_after - info.not_before == dt.timedelta(days=30)


def test_default_host_lifetime_is_a_year(tmp_path):
    """Without `days`, a host certificate lasts 365 days."""
    nuc = read_cert(issue(tmp_path, {"nuc": []}).identities["nuc"][0])
    assert nuc.not_after - nuc.not_before == dt.timedelta(days=365)


def test_issue_refuses_to_replace_any_file_and_then_writes_nothing(tmp_path):
    """One existing file of the set (here base.key) is enough: BadInput naming it, and neither the
    other files nor the folder's contents change; with force the whole set is replaced."""
    out = tmp_path / "certs"
    out.mkdir()
    (out / "base.key").write_text("old key\n")
    (out / "unrelated.txt").write_text("keep\n")
    with pytest.raises(BadInput, match=r"base\.key: already exists \(pass --force"):
        issue(out, {"nuc": [], "base": []})
    assert sorted(p.name for p in out.iterdir()) == ["base.key", "unrelated.txt"]
    assert (out / "base.key").read_text() == "old key\n"
    issued = issue(out, {"nuc": [], "base": []}, force=True)
    assert key_matches(read_cert(issued.identities["base"][0]), read_private_key(out / "base.key"))
    assert mode(out / "base.key") == 0o600
    assert (out / "unrelated.txt").read_text() == "keep\n"


def test_issue_refuses_an_existing_ca_and_a_monitor_file(tmp_path):
    """ca.pem counts as part of the set, and so do the monitor's files when the monitor is asked for
    (but not when it is not)."""
    issue(tmp_path, {"nuc": []})
    with pytest.raises(BadInput, match=r"ca\.pem: already exists"):
        issue(tmp_path, {"other": []})
    assert not (tmp_path / "other.pem").exists()
    (tmp_path / "ca.pem").unlink()
    (tmp_path / "nuc.pem").unlink()
    (tmp_path / "nuc.key").unlink()
    (tmp_path / f"{MONITOR}.key").write_text("x")
    with pytest.raises(BadInput, match=rf"{MONITOR}\.key: already exists"):
        issue(tmp_path, {"nuc": []}, monitor=True)
    assert not (tmp_path / "ca.pem").exists()
    issue(tmp_path, {"nuc": []})  # without the monitor its files are not in the way
    assert (tmp_path / f"{MONITOR}.key").read_text() == "x"


def test_read_cert_and_key_name_the_file_for_missing_and_non_pem_files(tmp_path, issued):
    """A missing file, a text file, a key read as a certificate and a certificate read as a key are
    BadInput naming the file."""
    missing = tmp_path / "missing.pem"
    with pytest.raises(BadInput, match=rf"^{missing}: no such file$"):
        read_cert(missing)
    with pytest.raises(BadInput, match=rf"^{missing}: no such file$"):
        read_private_key(missing)
    junk = tmp_path / "junk.pem"
    junk.write_text("hello\n")
    with pytest.raises(BadInput, match=rf"^{junk}: not a PEM certificate$"):
        read_cert(junk)
    with pytest.raises(BadInput, match=rf"^{junk}: not a PEM private key$"):
        read_private_key(junk)
    cert, key = issued.identities["nuc"]
    with pytest.raises(BadInput, match=rf"^{key}: not a PEM certificate$"):
        read_cert(key)
    with pytest.raises(BadInput, match=rf"^{cert}: not a PEM private key$"):
        read_private_key(cert)
    with pytest.raises(BadInput, match=rf"^{tmp_path}: not a regular file$"):
        read_cert(tmp_path)
    fifo = tmp_path / "fifo.pem"
    os.mkfifo(fifo)
    with pytest.raises(BadInput, match=rf"^{fifo}: not a regular file$"):  # never waits for a writer
        read_private_key(fifo)


def test_a_file_of_several_certificates_is_refused(tmp_path, issued):
    """TLS trusts every certificate of a CA file while a check would look at the first only: a
    bundle (the old CA appended during a rotation) is one BadInput saying how many it holds."""
    bundle = tmp_path / "bundle.pem"
    other = issue(tmp_path / "old", {"nuc": []})
    bundle.write_bytes(issued.ca.read_bytes() + other.ca.read_bytes())
    with pytest.raises(BadInput, match=rf"^{bundle}: holds 2 certificates"):
        read_cert(bundle)


def test_an_ip_written_as_a_dns_name_covers_nothing(tmp_path):
    """TLS matches an IP only against IP names: a certificate carrying 10.0.0.5 as a DNS name (made
    here with cryptography directly) does not cover 10.0.0.5."""
    ca = issue(tmp_path / "ca", {"nuc": []})
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "nuc")])
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(1)
        .not_valid_before(now)
        .not_valid_after(now + dt.timedelta(days=1))
        .add_extension(x509.SubjectAlternativeName([x509.DNSName("10.0.0.5")]), critical=False)
        .sign(key, hashes.SHA256())
    )
    path = tmp_path / "dns-ip.pem"
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    info = read_cert(path)
    assert info.dns_names == ("10.0.0.5",) and not info.covers("10.0.0.5")
    assert ca.ca.exists()


def test_names_and_lifetimes_that_no_certificate_can_carry_are_refused_before_writing(tmp_path):
    """A non-ASCII or malformed name, a host name over 64 characters, or host certificates outliving
    the CA: one BadInput each, and nothing written."""
    for names, days, message in (
        ({"nuc": ["nüc.lab"]}, 365, "nuc=nüc.lab: not an IP address or an ASCII DNS name"),
        ({"nuc": ["bad_name.lab"]}, 365, "nuc=bad_name.lab: not an IP address"),
        ({"n" * 65: []}, 365, "is longer than a certificate name may be"),
        ({"nuc": []}, 1826, "lasts 1 to 1825 days"),
    ):
        out = tmp_path / "out"
        with pytest.raises(BadInput, match=re.escape(message)):
            issue(out, names, days=days)
        assert not out.exists()


def test_an_encrypted_key_is_refused_with_its_file_named(tmp_path):
    """Hosts start unattended: a passphrase-protected key is BadInput saying it is encrypted."""
    key = ec.generate_private_key(ec.SECP256R1())
    path = tmp_path / "locked.key"
    path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.BestAvailableEncryption(b"secret passphrase"),
        )
    )
    with pytest.raises(BadInput, match=rf"^{path}: the private key is encrypted"):
        read_private_key(path)


OPENSSL = shutil.which("openssl")


def test_openssl_verifies_the_chain_names_and_purposes(tmp_path):
    """An independent verifier agrees: each certificate chains to ca.pem (not to another set's CA),
    nuc's covers its IP and DNS name, and the monitor is a client but not a server. Without the
    openssl binary there is no independent verifier: the test fails saying so (`make test`
    installs it as root), unless ROVER_SKIP_OPENSSL=1 asks for a skip."""
    if OPENSSL is None:
        missing = "no openssl binary, the independent verifier: apt-get install openssl (Debian package)"
        if os.environ.get("ROVER_SKIP_OPENSSL") == "1":
            pytest.skip(f"ROVER_SKIP_OPENSSL=1: skipped although {missing}")
        pytest.fail(missing, pytrace=False)
    issued = issue(tmp_path / "a", {"nuc": ["10.0.0.1", "nuc.lab"], "base": []}, monitor=True)
    other = issue(tmp_path / "b", {"nuc": ["10.0.0.1"]})

    def verify(cert, *options, ca=issued.ca):
        proc = subprocess.run(
            [str(OPENSSL), "verify", *options, "-CAfile", str(ca), str(cert)],
            capture_output=True,
            text=True,
            timeout=30,
        )
        return proc.returncode == 0 and proc.stdout.strip() == f"{cert}: OK", proc.stdout + proc.stderr

    nuc, base, monitor = (issued.identities[n][0] for n in ("nuc", "base", MONITOR))
    for cert in (nuc, base, monitor):
        ok, out = verify(cert)
        assert ok, out
    assert verify(nuc, "-purpose", "sslserver", "-verify_ip", "10.0.0.1")[0]
    assert verify(nuc, "-purpose", "sslclient", "-verify_hostname", "nuc.lab")[0]
    assert not verify(nuc, "-verify_ip", "10.0.0.2")[0]
    assert not verify(base, "-verify_hostname", "nuc.lab")[0]
    assert verify(monitor, "-purpose", "sslclient")[0]
    assert not verify(monitor, "-purpose", "sslserver")[0]
    assert not verify(nuc, ca=other.ca)[0]
    assert not verify(other.identities["nuc"][0])[0]


# -- `rover certs`, the real command


def test_cli_certs_issues_the_named_hosts_and_prints_a_security_section(tmp_path):
    """`rover certs --hosts --names --days -o`: exit 0, the given names (IPv6 too) in the SANs, the
    given lifetime, no monitor unless asked, and a security: section that is valid YAML naming the
    files. Run again without --force: exit 2 naming ca.pem, and the set is untouched."""
    out = tmp_path / "pki"
    args = ["certs", "--hosts", "nuc,base", "--names", "nuc=10.0.0.5,nuc=nuc.lab", "--names", "base=fd00::2"]
    proc = run_rover(*args, "--days", "10", "-o", str(out))
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in out.iterdir()) == ["base.key", "base.pem", "ca.pem", "nuc.key", "nuc.pem"]
    nuc, base = read_cert(out / "nuc.pem"), read_cert(out / "base.pem")
    assert sorted(nuc.names) == ["10.0.0.5", "nuc", "nuc.lab"]
    assert sorted(base.names) == ["base", "fd00::2"]
    assert nuc.not_after - nuc.not_before == dt.timedelta(days=10)
    assert read_cert(out / "ca.pem").not_after - nuc.not_before == dt.timedelta(days=CA_DAYS)
    section = yaml.safe_load(proc.stdout[proc.stdout.index("security:") :])
    assert section == {
        "security": {
            "ca": f"{out}/ca.pem",
            "hosts": {h: {"cert": f"{out}/{h}.pem", "key": f"{out}/{h}.key"} for h in ("nuc", "base")},
        }
    }
    before = (out / "ca.pem").read_bytes()
    again = run_rover(*args, "-o", str(out))
    assert again.returncode == 2
    [line] = again.stderr.splitlines()
    assert line.startswith(f"rover: error: {out}/ca.pem: already exists (pass --force")
    assert (out / "ca.pem").read_bytes() == before


HOSTS = """\
name: sec
hosts:
  nuc: {listen: ["tls/10.0.0.1:7447"]}
  base: {connect: ["tls/10.0.0.1:7447"]}
  laptop: {connect: ["tls/nuc.lab:7447"]}
"""
SECURITY = security_block(Path("pki"), monitor=False)
OPERATORS = """\
operators:
  tick: {uses: toyops.Ticker, host: nuc}
"""


def test_cli_certs_lists_each_name_derived_from_the_pipeline_once(tmp_path):
    """Names taken from the endpoints (nuc listens on 10.0.0.1 and base connects there; the laptop
    dials nuc.lab) are in the certificate and printed as it holds them: each once."""
    pipeline = tmp_path / "sec.yaml"
    pipeline.write_text(HOSTS + SECURITY + OPERATORS)
    out = tmp_path / "pki"
    proc = run_rover("certs", str(pipeline), "-o", str(out))
    assert proc.returncode == 0, proc.stderr
    assert sorted(read_cert(out / "nuc.pem").names) == ["10.0.0.1", "nuc", "nuc.lab"]
    assert f"{out}/nuc.pem, {out}/nuc.key: nuc (names: nuc, 10.0.0.1, nuc.lab)" in proc.stdout.splitlines()


def test_cli_certs_refuses_a_host_the_pipeline_does_not_declare(tmp_path):
    pipeline = tmp_path / "sec.yaml"
    pipeline.write_text(HOSTS + SECURITY + OPERATORS)
    out = tmp_path / "pki"
    proc = run_rover("certs", str(pipeline), "--hosts", "nuc,laptpo", "-o", str(out))
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [
        f"rover: error: --hosts: {pipeline} declares no host 'laptpo'; did you mean 'laptop'? "
        "(hosts: nuc, base, laptop): a certificate for it would serve no host of the pipeline"
    ]
    assert not out.exists()


def test_cli_certs_accepts_a_pipeline_with_tls_endpoints_and_no_security_section_yet(tmp_path):
    """The first step of securing a pipeline: its endpoints are tls/, the security: section does not
    exist yet, and `rover certs PIPELINE` makes the certificates (names from the endpoints)."""
    pipeline = tmp_path / "sec.yaml"
    pipeline.write_text(HOSTS + OPERATORS)
    out = tmp_path / "pki"
    proc = run_rover("certs", str(pipeline), "-o", str(out))
    assert proc.returncode == 0, proc.stderr
    assert sorted(read_cert(out / "nuc.pem").names) == ["10.0.0.1", "nuc", "nuc.lab"]

"""The certificate checks of `security:` (`rover check`, `rover status`): each defect of a CA,
certificate or key is one problem naming the file, at the line of the pipeline that names it."""

from __future__ import annotations

import datetime as dt
import re
import shutil
from pathlib import Path

import yaml
from helpers import run_rover

from rover.pipeline.spec import PipelineSpec, parse, read_document
from rover.pipeline.validation import served_addresses
from rover.security.certs import issue, read_cert
from rover.security.check import check_security

PIPELINE = """\
name: sec
vars: {certs: CERTDIR, out: out}
hosts:
  nuc: {listen: ["tls/10.0.0.1:7447"]}
  base: {connect: ["tls/10.0.0.1:7447"]}
  laptop: {connect: ["tls/nuc.lab:7447"]}
security:
  ca: ${certs}/ca.pem
  hosts:
    nuc: {cert: "${certs}/nuc.pem", key: "${certs}/nuc.key"}
    base: {cert: "${certs}/base.pem", key: "${certs}/base.key"}
    laptop: {cert: "${certs}/laptop.pem", key: "${certs}/laptop.key"}
  monitor: {cert: "${certs}/monitor.pem", key: "${certs}/monitor.key"}
operators:
  tick: {uses: toyops.Ticker, host: nuc}
  pass: {uses: toyops.Passthrough, host: base, inputs: {imu: tick/imu}}
  record: {uses: recorder, host: laptop, inputs: {imu: pass/imu}, params: {out: "${out}"}}
"""
NAMES = {"nuc": ["10.0.0.1", "nuc.lab"], "base": [], "laptop": []}
"""what `rover certs` derives from PIPELINE: nuc is reached at its IP (base) and at nuc.lab (laptop)"""
PROBLEM_LINE = re.compile(r"^(?P<file>[^:]+):(?P<line>\d+):(?P<col>\d+): (?P<path>/[^:]+): (?P<text>.+)$")


def real_now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def write_pipeline(tmp_path: Path, text: str = PIPELINE, certs: Path | None = None) -> Path:
    path = tmp_path / "sec.yaml"
    path.write_text(text.replace("CERTDIR", str(certs or tmp_path / "certs")))
    return path


def make_set(tmp_path: Path, names=None, **kwargs) -> Path:
    """A CA, the three hosts' identities and the monitor's in tmp_path/certs; that folder."""
    out = tmp_path / "certs"
    issue(out, NAMES if names is None else names, monitor=True, label="rover sec", **kwargs)
    return out


def load(pipeline: Path) -> PipelineSpec:
    spec, problems = parse(read_document(pipeline))
    assert problems == []
    return spec


def position(marker: str, value: str) -> tuple[int, int]:
    """1-based line and column of `value` on the (only) line of PIPELINE containing `marker`."""
    lines = [(i, line) for i, line in enumerate(PIPELINE.splitlines(), 1) if marker in line]
    assert len(lines) == 1, marker
    number, line = lines[0]
    assert value in line, (value, line)
    return number, line.index(value) + 1


CERT_OF = {h: position(f"{h}: {{cert:", f'"${{certs}}/{h}.pem"') for h in ("nuc", "base", "laptop", "monitor")}
KEY_OF = {h: position(f"{h}: {{cert:", f'"${{certs}}/{h}.key"') for h in ("nuc", "base", "laptop", "monitor")}
CA_AT = position("ca: ${certs}", "${certs}/ca.pem")


def where(diag) -> tuple[int, int]:
    return diag.line, diag.col


def test_a_fresh_set_passes_every_check_including_the_monitor(tmp_path):
    """Certificates issued for the pipeline's names: no problem and no warning, hosts and monitor alike."""
    certs = make_set(tmp_path)
    spec = load(write_pipeline(tmp_path))
    assert spec.security is not None and spec.security.ca == f"{certs}/ca.pem"
    assert check_security(spec, monitor=True) == ([], [])


def test_nucs_certificate_must_cover_its_ip_and_the_dns_name_the_laptop_uses(tmp_path):
    """served_addresses of nuc: the address it listens on, the one base connects to and the DNS name
    the laptop connects to (tls/nuc.lab resolves to no one else's listener); the leaves serve none.
    The certificate issued with those names covers every one of them."""
    certs = make_set(tmp_path)
    spec = load(write_pipeline(tmp_path))
    served = served_addresses(spec, "nuc")
    assert sorted(served) == [
        ("10.0.0.1", "base connects to tls/10.0.0.1:7447"),
        ("10.0.0.1", "nuc listens on tls/10.0.0.1:7447"),
        ("nuc.lab", "laptop connects to tls/nuc.lab:7447"),
    ]
    assert served_addresses(spec, "base") == served_addresses(spec, "laptop") == []
    nuc = read_cert(certs / "nuc.pem")
    assert all(nuc.covers(address) for address, _why in served)


def test_an_expired_host_certificate_is_one_problem_naming_the_file(tmp_path):
    """Issued 3 days ago for 1 day: nuc's certificate alone (the CA is valid 5 years) gives exactly
    one problem, at the line of nuc's cert:, naming the file and when it expired."""
    certs = make_set(tmp_path, now=real_now() - dt.timedelta(days=3), days=1)
    spec = load(write_pipeline(tmp_path))
    problems, warnings = check_security(spec, ["nuc"])
    assert warnings == []
    [problem] = problems
    expiry = read_cert(certs / "nuc.pem").not_after.strftime("%Y-%m-%d %H:%M UTC")
    assert problem.message == f"{certs}/nuc.pem: the certificate of host nuc expired on {expiry}"
    assert where(problem) == CERT_OF["nuc"]
    everyone, _ = check_security(spec, monitor=True)
    assert sorted((where(p), p.message.split(":")[0]) for p in everyone) == sorted(
        (CERT_OF[h], f"{certs}/{h}.pem") for h in ("nuc", "base", "laptop", "monitor")
    )
    assert all("expired on" in p.message for p in everyone)


def test_expiry_is_judged_at_now(tmp_path):
    """A set of 100 days is fine after 50 and expired after 101 (the CA still valid): a checker that
    ignored the date would pass both."""
    start = real_now()
    make_set(tmp_path, days=100, now=start)
    spec = load(write_pipeline(tmp_path))
    assert check_security(spec, ["base"], now=start + dt.timedelta(days=50)) == ([], [])
    [problem], warnings = check_security(spec, ["base"], now=start + dt.timedelta(days=101))
    assert "base.pem: the certificate of host base expired on" in problem.message
    assert warnings == []


def test_a_certificate_close_to_its_end_is_a_warning(tmp_path):
    """Within 30 days of its end a host's (or the monitor's) certificate still passes, with a warning
    naming the file, the days left and the date."""
    start = real_now()
    certs = make_set(tmp_path, days=100, now=start)
    spec = load(write_pipeline(tmp_path))
    end = read_cert(certs / "base.pem").not_after
    problems, warnings = check_security(spec, ["base"], now=start + dt.timedelta(days=80))
    assert problems == []
    assert warnings == [
        f"{certs}/base.pem: warning: the certificate of host base expires in 19 days "
        f"({end.strftime('%Y-%m-%d %H:%M UTC')})"
    ]
    problems, warnings = check_security(spec, [], monitor=True, now=start + dt.timedelta(days=80))
    assert problems == [] and [w.split(": ")[0] for w in warnings] == [f"{certs}/monitor.pem"]


def test_a_ca_close_to_its_end_is_a_warning(tmp_path):
    """The CA 10 days from its end (nuc's certificate, as long-lived as allowed, too): a warning
    naming ca.pem, and one naming nuc.pem."""
    certs = make_set(tmp_path, days=1825, now=real_now() - dt.timedelta(days=1815))
    spec = load(write_pipeline(tmp_path))
    problems, warnings = check_security(spec, ["nuc"])
    assert problems == []
    assert [w.split(": ")[0] for w in warnings] == [f"{certs}/ca.pem", f"{certs}/nuc.pem"]


def test_a_certificate_not_yet_valid_blames_the_clock(tmp_path):
    """Issued two days ahead, the CA and nuc's certificate are both not valid yet: one problem each,
    at their own lines, asking whether the clock is right."""
    certs = make_set(tmp_path, now=real_now() + dt.timedelta(days=2))
    spec = load(write_pipeline(tmp_path))
    problems, _ = check_security(spec, ["nuc"])
    assert [(where(p), p.message.split(": ")[0]) for p in problems] == [
        (CA_AT, f"{certs}/ca.pem"),
        (CERT_OF["nuc"], f"{certs}/nuc.pem"),
    ]
    assert "the CA certificate is not valid before" in problems[0].message
    assert "the certificate of host nuc is not valid before" in problems[1].message
    assert all(p.message.endswith("(is this clock right?)") for p in problems)


def test_a_certificate_without_the_dns_name_names_the_address_and_who_connects(tmp_path):
    """nuc's certificate lacks nuc.lab: one problem naming the file, nuc.lab, the laptop's endpoint
    and the names the certificate does have."""
    certs = make_set(tmp_path, names={**NAMES, "nuc": ["10.0.0.1"]})
    spec = load(write_pipeline(tmp_path))
    [problem], _ = check_security(spec, ["nuc"])
    assert where(problem) == CERT_OF["nuc"]
    assert problem.message == (
        f"{certs}/nuc.pem: the certificate of host nuc does not cover nuc.lab "
        "(laptop connects to tls/nuc.lab:7447); its names: DNS:nuc, IP:10.0.0.1"
    )


def test_a_certificate_without_the_ip_names_base_as_the_one_connecting(tmp_path):
    """nuc's certificate lacks 10.0.0.1: the problems name the file and 10.0.0.1, one of them says
    base connects there, and nothing else of the set is blamed."""
    certs = make_set(tmp_path, names={**NAMES, "nuc": ["nuc.lab"]})
    spec = load(write_pipeline(tmp_path))
    problems, _ = check_security(spec, monitor=True)
    assert problems
    assert all(p.message.startswith(f"{certs}/nuc.pem: ") and "does not cover 10.0.0.1" in p.message for p in problems)
    assert any("base connects to tls/10.0.0.1:7447" in p.message for p in problems)


def test_a_missing_ip_is_one_problem_even_when_two_endpoints_use_it(tmp_path):
    """One defect (10.0.0.1 missing from nuc's certificate) is one problem line, though nuc listens
    there and base connects there."""
    make_set(tmp_path, names={**NAMES, "nuc": ["nuc.lab"]})
    spec = load(write_pipeline(tmp_path))
    problems, _ = check_security(spec, monitor=True)
    assert len(problems) == 1, [p.message for p in problems]


def test_a_certificate_of_another_host_is_refused_by_its_common_name(tmp_path):
    """base's certificate and key copied over nuc's (base's certificate even covers nuc's names, so
    only the identity is wrong): one problem saying it is base's, not nuc's."""
    certs = make_set(tmp_path, names={**NAMES, "base": ["10.0.0.1", "nuc.lab"]})
    shutil.copy(certs / "base.pem", certs / "nuc.pem")
    shutil.copy(certs / "base.key", certs / "nuc.key")
    spec = load(write_pipeline(tmp_path))
    [problem], _ = check_security(spec, monitor=True)
    assert where(problem) == CERT_OF["nuc"]
    assert problem.message == (
        f"{certs}/nuc.pem: the certificate of host nuc is for 'base', not 'nuc' (its common name)"
    )


def test_the_monitor_identity_must_be_the_monitors(tmp_path):
    """A host's certificate and key given as the monitor's: one problem at the monitor's line."""
    certs = make_set(tmp_path)
    shutil.copy(certs / "laptop.pem", certs / "monitor.pem")
    shutil.copy(certs / "laptop.key", certs / "monitor.key")
    spec = load(write_pipeline(tmp_path))
    assert check_security(spec) == ([], [])  # the monitor is checked only when asked for
    [problem], _ = check_security(spec, [], monitor=True)
    assert where(problem) == CERT_OF["monitor"]
    assert "the certificate of the monitor is for 'laptop', not 'monitor'" in problem.message


def test_a_certificate_from_another_ca_is_refused(tmp_path):
    """nuc's certificate and key from a second issue() (same names, same CA name): one problem, not
    signed by the CA in ca.pem."""
    certs = make_set(tmp_path)
    other = issue(tmp_path / "other", NAMES, label="rover sec")
    shutil.copy(other.identities["nuc"][0], certs / "nuc.pem")
    shutil.copy(other.identities["nuc"][1], certs / "nuc.key")
    spec = load(write_pipeline(tmp_path))
    [problem], _ = check_security(spec, monitor=True)
    assert where(problem) == CERT_OF["nuc"]
    assert problem.message == f"{certs}/nuc.pem: the certificate of host nuc is not signed by the CA in {certs}/ca.pem"


def test_a_key_that_is_not_the_certificates_is_refused(tmp_path):
    """base's key in place of nuc's: one problem naming the key file and the certificate."""
    certs = make_set(tmp_path)
    shutil.copy(certs / "base.key", certs / "nuc.key")
    spec = load(write_pipeline(tmp_path))
    [problem], _ = check_security(spec, monitor=True)
    assert problem.line == CERT_OF["nuc"][0]
    assert problem.message == f"{certs}/nuc.key: this private key does not belong to {certs}/nuc.pem"


def test_a_missing_key_file_is_one_problem_at_the_key(tmp_path):
    """nuc.key deleted: one problem, at the key: value, saying there is no such file."""
    certs = make_set(tmp_path)
    (certs / "nuc.key").unlink()
    spec = load(write_pipeline(tmp_path))
    [problem], _ = check_security(spec, monitor=True)
    assert where(problem) == KEY_OF["nuc"]
    assert problem.message == f"{certs}/nuc.key: no such file"


def test_a_missing_ca_is_one_problem_not_one_per_host(tmp_path):
    """ca.pem deleted: one problem at ca:, and no host is blamed for a signature that cannot be checked."""
    certs = make_set(tmp_path)
    (certs / "ca.pem").unlink()
    spec = load(write_pipeline(tmp_path))
    [problem], _ = check_security(spec, monitor=True)
    assert where(problem) == CA_AT
    assert problem.message == f"{certs}/ca.pem: no such file"


def test_a_key_readable_by_others_is_a_warning_not_a_problem(tmp_path):
    """nuc.key of mode 0640: no problem, one warning naming the file, its mode and the fix."""
    certs = make_set(tmp_path)
    (certs / "nuc.key").chmod(0o640)
    spec = load(write_pipeline(tmp_path))
    assert check_security(spec, monitor=True) == (
        [],
        [f"{certs}/nuc.key: warning: private key readable by others (mode 0640); chmod 600"],
    )


def test_only_the_named_hosts_are_checked(tmp_path):
    """With hosts=['base'] the laptop's missing key does not count (a deployed base holds only its own);
    without, it does; the CA is checked either way."""
    certs = make_set(tmp_path)
    (certs / "laptop.key").unlink()
    spec = load(write_pipeline(tmp_path))
    assert check_security(spec, ["base"]) == ([], [])
    [problem], _ = check_security(spec)
    assert problem.message == f"{certs}/laptop.key: no such file"
    (certs / "ca.pem").unlink()
    [problem], _ = check_security(spec, ["base"])
    assert problem.message == f"{certs}/ca.pem: no such file"


def test_a_pipeline_without_security_has_nothing_to_check(tmp_path):
    """No security: section, no checks (even with monitor=True)."""
    text = PIPELINE.split("security:")[0] + "operators:" + PIPELINE.split("operators:")[1]
    spec = load(write_pipeline(tmp_path, text.replace("tls/", "tcp/")))
    assert spec.security is None
    assert check_security(spec, monitor=True) == ([], [])


def test_the_monitor_is_required_only_when_asked_for(tmp_path):
    """Without a monitor: entry, check_security(monitor=True) gives one problem at security: pointing
    at `rover certs --monitor`; without monitor=True, none."""
    make_set(tmp_path)
    text = "\n".join(line for line in PIPELINE.splitlines() if not line.startswith("  monitor:"))
    spec = load(write_pipeline(tmp_path, text))
    assert check_security(spec) == ([], [])
    [problem], _ = check_security(spec, [], monitor=True)
    assert problem.line in (position("security:", "security:")[0], CA_AT[0])  # the section or its first line
    assert "no monitor: identity (rover certs --monitor)" in problem.message


# -- the real command line


def problem_lines(stderr: str, pipeline: Path) -> list[re.Match]:
    """The stderr lines of `rover check` problems, each FILE:LINE:COL: PATH: TEXT, and the count line."""
    lines = stderr.splitlines()
    assert lines, "no problem reported"
    count = len(lines) - 1
    assert lines[-1] == f"{count} problem{'s' if count > 1 else ''} found", stderr
    found = [PROBLEM_LINE.match(line) for line in lines[:-1]]
    matches = [m for m in found if m is not None]
    assert len(matches) == len(found), stderr
    assert all(m["file"] == str(pipeline) for m in matches), stderr
    return matches


def test_cli_certs_for_the_pipeline_then_check_passes_and_prints_the_rules(tmp_path):
    """`rover certs PIPELINE --monitor` takes nuc's names from the endpoints; `rover check --security`
    on the result exits 0, says mutual TLS, and prints the rules, e.g. what nuc accepts from base."""
    pipeline = write_pipeline(tmp_path)
    certs = tmp_path / "certs"
    made = run_rover("certs", str(pipeline), "--monitor", "-o", str(certs))
    assert made.returncode == 0, made.stderr
    assert f"  monitor: {{cert: {certs}/monitor.pem, key: {certs}/monitor.key}}" in made.stdout
    assert sorted(read_cert(certs / "nuc.pem").names) == ["10.0.0.1", "nuc", "nuc.lab"]
    proc = run_rover("check", str(pipeline), "--security")
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    summary, *rules = proc.stdout.splitlines()
    assert summary.startswith(f"{pipeline}: ok: pipeline 'sec'")
    assert summary.endswith("; mutual TLS, certificates of every host valid")
    nuc = rules[rules.index("host nuc:") + 1 : rules.index("host base:")]
    assert "  put from base: _ack/pass/imu, _hosts/base/**, pass/imu" in nuc
    assert "  put to laptop: _hosts/base/**, _hosts/nuc/**, pass/imu" in nuc
    assert "  query from monitor: _status/**" in nuc


def test_cli_reports_one_line_per_defect_at_its_position(tmp_path):
    """Three defects at once (nuc's certificate from another CA, base's key not its own, the
    laptop's key missing): exit 2, exactly three problem lines FILE:LINE:COL: PATH: ..., each at
    the line naming that file, then '3 problems found'."""
    certs = make_set(tmp_path)
    other = issue(tmp_path / "other", NAMES)
    shutil.copy(other.identities["nuc"][0], certs / "nuc.pem")
    shutil.copy(other.identities["nuc"][1], certs / "nuc.key")
    shutil.copy(certs / "monitor.key", certs / "base.key")
    (certs / "laptop.key").unlink()
    pipeline = write_pipeline(tmp_path)
    proc = run_rover("check", str(pipeline))
    assert proc.returncode == 2, proc.stderr
    assert proc.stdout == ""
    found = {m["path"]: (int(m["line"]), int(m["col"]), m["text"]) for m in problem_lines(proc.stderr, pipeline)}
    assert found == {
        f"{certs}/nuc.pem": (*CERT_OF["nuc"], f"the certificate of host nuc is not signed by the CA in {certs}/ca.pem"),
        f"{certs}/base.key": (*found[f"{certs}/base.key"][:2], f"this private key does not belong to {certs}/base.pem"),
        f"{certs}/laptop.key": (*KEY_OF["laptop"], "no such file"),
    }
    assert found[f"{certs}/base.key"][0] == CERT_OF["base"][0]  # on base's line (at its cert: or its key:)


def test_cli_expired_certificate_of_one_host(tmp_path):
    """A set issued 3 days ago for 1 day, checked for nuc only: one line naming nuc.pem and
    'expired', then '1 problem found'."""
    certs = make_set(tmp_path, now=real_now() - dt.timedelta(days=3), days=1)
    pipeline = write_pipeline(tmp_path)
    proc = run_rover("check", str(pipeline), "--host", "nuc")
    assert proc.returncode == 2, proc.stderr
    [match] = problem_lines(proc.stderr, pipeline)
    assert (int(match["line"]), int(match["col"])) == CERT_OF["nuc"]
    assert match["path"] == f"{certs}/nuc.pem"
    assert match["text"].startswith("the certificate of host nuc expired on ")


def test_cli_a_group_readable_key_warns_but_passes(tmp_path):
    """nuc.key of mode 0640: exit 0, the summary on stdout, the warning on stderr."""
    certs = make_set(tmp_path)
    (certs / "nuc.key").chmod(0o640)
    pipeline = write_pipeline(tmp_path)
    proc = run_rover("check", str(pipeline))
    assert proc.returncode == 0, proc.stderr
    assert "mutual TLS" in proc.stdout
    assert proc.stderr.splitlines() == [
        f"{certs}/nuc.key: warning: private key readable by others (mode 0640); chmod 600"
    ]


def test_cli_check_host_checks_only_that_hosts_identity(tmp_path):
    """The laptop's key deleted: `rover check --host base` passes (and says whose certificates it
    checked); plain `rover check` fails naming laptop.key."""
    certs = make_set(tmp_path)
    (certs / "laptop.key").unlink()
    pipeline = write_pipeline(tmp_path)
    only_base = run_rover("check", str(pipeline), "--host", "base")
    assert only_base.returncode == 0, only_base.stderr
    assert only_base.stdout.rstrip().endswith("; mutual TLS, certificates of base valid")
    everyone = run_rover("check", str(pipeline))
    assert everyone.returncode == 2
    [match] = problem_lines(everyone.stderr, pipeline)
    assert (match["path"], match["text"]) == (f"{certs}/laptop.key", "no such file")


def test_cli_status_under_security_needs_the_monitor_identity(tmp_path):
    """`rover status --once` on a secured pipeline without a monitor: entry exits 2 before
    connecting, with one line about the monitor identity."""
    make_set(tmp_path)
    text = "\n".join(line for line in PIPELINE.splitlines() if not line.startswith("  monitor:"))
    pipeline = write_pipeline(tmp_path, text)
    proc = run_rover("status", str(pipeline), "--once", "--timeout", "0.5", timeout=30)
    assert proc.returncode == 2, proc.stderr
    [line] = proc.stderr.splitlines()
    assert line.startswith(f"{pipeline}:") and "no monitor: identity" in line
    assert "rover certs --monitor" in line


def test_cli_run_refuses_to_start_a_host_with_an_expired_certificate(tmp_path):
    """`rover run --host nuc` with nuc's certificate expired exits 2 with that one problem before
    it opens a session (no output folder); with a valid set, base's missing key stops
    `rover run --host base` the same way."""
    certs = make_set(tmp_path, now=real_now() - dt.timedelta(days=3), days=1)
    pipeline = write_pipeline(tmp_path)
    out = tmp_path / "out"
    proc = run_rover("run", str(pipeline), "--host", "nuc", "--set", f"out={out}", timeout=60)
    assert proc.returncode == 2, proc.stderr
    [match] = [PROBLEM_LINE.match(line) for line in proc.stderr.splitlines()]
    assert match is not None, proc.stderr
    assert match["path"] == f"{certs}/nuc.pem" and "expired on" in match["text"]
    assert not out.exists()
    make_set(tmp_path, force=True)  # a valid set, but for base's key
    (certs / "base.key").unlink()
    proc = run_rover("run", str(pipeline), "--host", "base", "--set", f"out={out}", timeout=60)
    assert proc.returncode == 2, proc.stderr
    found = [PROBLEM_LINE.match(line) for line in proc.stderr.splitlines()]
    assert [(m["path"], m["text"]) for m in found if m] == [(f"{certs}/base.key", "no such file")], proc.stderr


def test_the_ca_certificate_in_a_hosts_place_is_refused_as_a_ca(tmp_path):
    """ca.pem copied over nuc.pem (webpki refuses a CA certificate as a leaf): among nuc's problems,
    one says it is a CA certificate."""
    certs = make_set(tmp_path)
    shutil.copy(certs / "ca.pem", certs / "nuc.pem")
    problems, _ = check_security(load(write_pipeline(tmp_path)), ["nuc"])
    assert any(
        p.message == f"{certs}/nuc.pem: the certificate of host nuc is a CA certificate, not a host's" for p in problems
    ), problems


def test_cli_certs_issues_a_host_named_twice_once(tmp_path):
    """`--hosts nuc,base,nuc`: two identities, and the printed security: block loads as YAML."""
    out = tmp_path / "pki"
    proc = run_rover("certs", "--hosts", "nuc,base,nuc", "-o", str(out))
    assert proc.returncode == 0, proc.stderr
    block = proc.stdout[proc.stdout.index("security:") :]
    assert sorted(yaml.safe_load(block)["security"]["hosts"]) == ["base", "nuc"]

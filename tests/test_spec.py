"""Loading pipeline files: positions, typed `${var}` substitution, command-line values."""

from __future__ import annotations

import pytest
from helpers import ROOT

from rover.cli.registry import BUILTINS
from rover.errors import SpecError
from rover.pipeline.spec import parse
from rover.pipeline.validation import check
from rover.pipeline.yamlpos import load, parse_scalar

TEXT = """\
name: demo
vars: {n: 3, out: results, speed: max}
operators:
  a:
    uses: recorder
    params: {out: "${out}/run-${n}", n: "${n}", speed: "${speed}"}
"""


def test_whole_value_substitution_keeps_the_type_partial_makes_a_string():
    spec, problems = parse(load(TEXT, "p.yaml"), {"n": 30})
    assert problems == []
    params = spec.operators["a"].params
    assert params == {"out": "results/run-30", "n": 30, "speed": "max"}


def test_positions_of_keys_and_values():
    doc = load(TEXT, "p.yaml")
    assert doc.key_at("operators", "a", "uses") == (5, 5)
    assert doc.at("operators", "a", "uses") == (5, 11)
    assert doc.at("operators", "a", "params", "n") == (6, 41)
    assert doc.at("operators", "a", "missing", "deep") == doc.at("operators", "a")


def test_command_line_values_are_typed_like_yaml():
    assert parse_scalar("30") == 30
    assert parse_scalar("0.5") == 0.5
    assert parse_scalar("max") == "max"
    assert parse_scalar("") == ""
    assert parse_scalar("true") is True
    assert parse_scalar("a: b") == "a: b"
    assert parse_scalar("[1, 2]") == [1, 2]
    assert parse_scalar("tcp/127.0.0.1:7447") == "tcp/127.0.0.1:7447"


def test_empty_file_reports_missing_operators():
    _spec, problems = parse(load("", "empty.yaml"))
    assert [p.message for p in problems] == ["the pipeline has no operators: section"]


SECURE = """\
name: sec
vars: {certs: /etc/rover}
hosts:
  nuc: {listen: ["tls/10.0.0.1:7447"]}
  base: {connect: ["tls/10.0.0.1:7447"]}
security:
  ca: ${certs}/ca.pem
  hosts:
    nuc: {cert: "${certs}/nuc.pem", key: "${certs}/nuc.key"}
    base: {cert: "${certs}/base.pem", key: "${certs}/base.key"}
  monitor: {cert: "${certs}/monitor.pem", key: "${certs}/monitor.key"}
operators: {}
"""


def secure(old: str, new: str) -> str:
    assert old in SECURE
    return SECURE.replace(old, new)


def test_security_paths_take_vars_and_give_the_identities():
    """`${certs}` in security: paths is substituted (also by --set); each host and the monitor get
    their cert and key."""
    spec, problems = parse(load(SECURE, "s.yaml"), {"certs": "/srv/pki"})
    assert problems == []
    assert spec.security is not None
    assert spec.security.ca == "/srv/pki/ca.pem"
    assert {h: (i.cert, i.key) for h, i in spec.security.hosts.items()} == {
        "nuc": ("/srv/pki/nuc.pem", "/srv/pki/nuc.key"),
        "base": ("/srv/pki/base.pem", "/srv/pki/base.key"),
    }
    monitor = spec.security.monitor
    assert monitor is not None
    assert (monitor.cert, monitor.key) == ("/srv/pki/monitor.pem", "/srv/pki/monitor.key")
    plain, _ = parse(load(SECURE.split("security:")[0] + "operators: {}\n", "s.yaml"))
    assert plain.security is None


def test_security_refuses_a_tcp_endpoint_and_suggests_tls():
    """With security:, base connecting over tcp/ is one problem at that endpoint naming the host and
    the tls/ endpoint to use instead."""
    text = secure('connect: ["tls/', 'connect: ["tcp/')
    _spec, problems = parse(load(text, "s.yaml"))
    assert [(p.line, p.col, p.message) for p in problems] == [
        (
            5,
            text.splitlines()[4].index('"tcp/') + 1,
            "host 'base' connects to tcp/10.0.0.1:7447: with security: every endpoint is tls/ (mutual TLS), "
            "e.g. tls/10.0.0.1:7447",
        )
    ]
    _spec, problems = parse(load(secure('listen: ["tls/', 'listen: ["tcp/'), "s.yaml"))
    assert [p.message.split(":")[0] for p in problems] == ["host 'nuc' listens on tcp/10.0.0.1"]


def test_security_needs_an_identity_for_every_host():
    """A host missing from security: hosts: is a problem naming it and the entry to add."""
    _spec, problems = parse(load(secure('    base: {cert: "${certs}/base.pem", key: "${certs}/base.key"}\n', ""), "s"))
    assert [p.message for p in problems] == [
        "security: host 'base' has no certificate (hosts: base: {cert: ..., key: ...})"
    ]


def test_security_refuses_an_undeclared_host_with_a_suggestion():
    """An entry under security: hosts: that is no declared host: a problem at its key, did-you-mean."""
    text = secure("    base: {cert:", "    bsae: {cert:")
    _spec, problems = parse(load(text, "s.yaml"))
    messages = [(p.line, p.col, p.message) for p in problems]
    assert (10, 5, "security: hosts: 'bsae' is not a declared host; did you mean 'base'?") in messages
    assert (8, 3, "security: host 'base' has no certificate (hosts: base: {cert: ..., key: ...})") in messages
    assert len(messages) == 2


def test_monitor_is_a_reserved_host_name_under_security():
    """A host called monitor would share the read-only identity's name: refused at the host's key,
    only when security: is there."""
    text = SECURE.replace("base", "monitor")
    _spec, problems = parse(load(text, "s.yaml"))
    assert [(p.line, p.col, p.message) for p in problems] == [
        (5, 3, "host name 'monitor' is reserved for the read-only identity under security:")
    ]
    plain = text.split("security:")[0].replace("tls/", "tcp/") + "operators: {}\n"
    _spec, problems = parse(load(plain, "s.yaml"))
    assert problems == []


def test_security_without_hosts_is_a_problem():
    """security: in a file without hosts: protects nothing: one problem, and no security in the spec."""
    spec, problems = parse(load("security:\n  ca: ca.pem\noperators: {}\n", "s.yaml"))
    assert [p.message for p in problems] == [
        "security: protects the links between hosts; this pipeline declares no hosts:"
    ]
    assert spec.security is None


def test_security_refuses_unknown_keys_with_a_suggestion():
    """A misspelt key (cas:) is reported at the key with did-you-mean; the missing ca: too."""
    _spec, problems = parse(load(secure("  ca: ", "  cas: "), "s.yaml"))
    messages = [p.message for p in problems]
    assert "unknown key 'cas' in security; did you mean 'ca'?" in messages
    assert "security: ca (the CA certificate, a PEM file) must be a non-empty string" in messages
    assert len(messages) == 2
    assert (problems[0].line, problems[0].col) == (7, 3)


def test_security_identity_needs_both_files():
    """An identity without key: is a problem at it; an undefined variable in a path is reported."""
    text = secure(', key: "${certs}/nuc.key"}', "}").replace("${certs}/base.pem", "${cert}/base.pem")
    _spec, problems = parse(load(text, "s.yaml"))
    messages = [p.message for p in problems]
    assert "security: host 'nuc': key must be a non-empty string" in messages
    assert any(m.startswith("undefined variable ${cert}; did you mean 'certs'?") for m in messages)
    assert len(messages) == 2


def test_tls_and_quic_endpoints_need_a_security_section():
    """Without security:, a tls/ or quic/ endpoint cannot open (no certificates): one problem per
    endpoint, at it; tcp/ is fine."""
    text = SECURE.split("security:")[0].replace('connect: ["tls/', 'connect: ["quic/') + "operators: {}\n"
    spec, problems = parse(load(text, "s.yaml"))
    assert problems == [], "parsing alone accepts them: `rover certs` reads such a file to make the certificates"
    with pytest.raises(SpecError) as caught:
        check(spec, BUILTINS, problems)
    problems = [p for p in caught.value.diagnostics if "needs certificates" in p.message]
    assert [(p.line, p.message.split(":")[0]) for p in problems] == [(4, "tls/10.0.0.1"), (5, "quic/10.0.0.1")]
    assert all("needs certificates: add a security: section" in p.message for p in problems)
    spec, problems = parse(load(text.replace("tls/", "tcp/").replace("quic/", "tcp/"), "s.yaml"))
    check(spec, BUILTINS, problems)


def test_security_refuses_an_ipv6_literal_in_a_tls_endpoint():
    """Zenoh's TLS cannot dial an IPv6 literal: under security: a tls/[...] endpoint is a problem at
    it that says to use a DNS name or IPv4."""
    text = secure('connect: ["tls/10.0.0.1:7447"]', 'connect: ["tls/[fd00::1]:7447"]')
    _spec, problems = parse(load(text, "s.yaml"))
    assert [(p.line, p.message.split(":")[0]) for p in problems] == [(5, "tls/[fd00")]
    assert "IPv6 literal" in problems[0].message and "IPv4" in problems[0].message


def test_security_refuses_endpoint_options_that_would_override_tls():
    """`#enable_mtls=false` (or any #option: Zenoh lets them override the TLS settings) under
    security: is a problem at that endpoint; without security: it is left alone."""
    text = secure('connect: ["tls/10.0.0.1:7447"]', 'connect: ["tls/10.0.0.1:7447#enable_mtls=false"]')
    _spec, problems = parse(load(text, "s.yaml"))
    assert [(p.line, "no #options" in p.message) for p in problems] == [(5, True)]
    plain = text.split("security:")[0].replace("tls/", "tcp/") + "operators: {}\n"
    assert parse(load(plain, "s.yaml"))[1] == []


def test_under_security_a_connect_endpoint_must_reach_one_host():
    """Base and the NUC both listen on a wildcard at port 7447 and the laptop dials an address:
    the link (so the access rules) would be a guess; under security: that is a problem at the
    laptop's endpoint naming both hosts; without security: the check accepts it, as before."""
    text = (
        SECURE.replace('nuc: {listen: ["tls/10.0.0.1:7447"]}', 'nuc: {listen: ["tls/0.0.0.0:7447"]}')
        .replace(
            'base: {connect: ["tls/10.0.0.1:7447"]}',
            'base: {listen: ["tls/0.0.0.0:7447"]}\n  laptop: {connect: ["tls/10.0.0.1:7447"]}',
        )
        .replace("  monitor:", '    laptop: {cert: "${certs}/laptop.pem", key: "${certs}/laptop.key"}\n  monitor:')
    )
    spec, problems = parse(load(text, "s.yaml"))
    assert problems == []
    with pytest.raises(SpecError) as caught:
        check(spec, BUILTINS, problems)
    [problem] = caught.value.diagnostics
    assert problem.line == 6 and "could be nuc or base" in problem.message, problem
    plain = text.split("security:")[0].replace("tls/", "tcp/") + "operators: {}\n"
    spec, problems = parse(load(plain, "s.yaml"))
    check(spec, BUILTINS, problems)


def test_a_set_of_a_variable_the_pipeline_neither_declares_nor_uses_is_refused_with_a_did_you_mean(capsys):
    from rover.cli.app import main

    pipeline = str(ROOT / "pipeline.yaml")
    assert main(["run", pipeline, "--set", "outptu=zzz"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"rover: error: --set outptu=...: {pipeline} has no variable 'outptu'; did you mean 'output'? "
        "(vars: dataset, output, port, setup, speed, timing_topic; OPERATOR.PARAM sets a param)"
    ]


def test_a_variable_used_but_not_declared_may_be_set():
    doc = load("name: p\noperators:\n  a: {uses: x, params: {n: '${n}'}}\n", "p.yaml")
    spec, _ = parse(doc, {"n": 3})
    assert spec.operators["a"].params == {"n": 3}

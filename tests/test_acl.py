"""Zenoh access control generated from the wiring: per link, what each neighbour may send in and
what a host sends out, bound to certificate common names; deny by default; the monitor reads status only."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh
from netns import security_block

import rover
from rover.pipeline.spec import MONITOR, parse, read_document
from rover.pipeline.validation import host_links
from rover.pipeline.yamlpos import load
from rover.security.acl import access_control, carried, describe, flows

OPERATORS = """\
operators:
  tick:   {uses: toyops.Ticker, host: nuc}
  watch:  {uses: toyops.Passthrough, host: nuc, inputs: {imu: btick/silent}}
  btick:  {uses: toyops.Ticker, host: base}
  pass:   {uses: toyops.Passthrough, host: base, inputs: {imu: tick/imu}}
  record: {uses: recorder, host: laptop, inputs: {imu: pass/imu, silent: tick/silent}, params: {out: out}}
"""
"""nuc -> base: tick/imu; base -> nuc: btick/silent; nuc -> laptop only: tick/silent; base -> laptop:
pass/imu; btick/imu and watch/imu nobody reads."""

SECURITY = security_block(Path("pki"), monitor=False)
"""the files need not exist: the rules come from the wiring alone"""

STAR = (
    """\
name: star
hosts:
  nuc:    {listen: ["tls/10.0.0.1:7447"]}
  base:   {connect: ["tls/10.0.0.1:7447"]}
  laptop: {connect: ["tls/10.0.0.1:7447"]}
"""
    + SECURITY
    + OPERATORS
)
MESH = (
    """\
name: mesh
hosts:
  nuc:    {listen: ["tls/10.0.0.1:7447"]}
  base:   {listen: ["tls/10.0.0.2:7448"], connect: ["tls/10.0.0.1:7447"]}
  laptop: {connect: ["tls/10.0.0.1:7447", "tls/10.0.0.2:7448"]}
"""
    + SECURITY
    + OPERATORS
)
HOSTS = ("nuc", "base", "laptop")


def spec_of(text):
    spec, problems = parse(load(text, "x.yaml"))
    assert problems == []
    return spec


@pytest.fixture(scope="module", params=["star", "mesh"])
def spec(request):
    return spec_of({"star": STAR, "mesh": MESH}[request.param])


def rule_keys(conf, other, flow, message) -> set[str]:
    """The key expressions `conf` allows for `message` in direction `flow` on its link with `other`."""
    policy = next(p for p in conf["policies"] if p["subjects"] == [f"host-{other}"])
    rules = {r["id"]: r for r in conf["rules"]}
    found: set[str] = set()
    for rid in policy["rules"]:
        rule = rules[rid]
        if message in rule["messages"] and flow in rule["flows"] and rule["permission"] == "allow":
            found |= set(rule["key_exprs"])
    return found


def short(name, keys) -> set[str]:
    prefix = f"rover/{name}/"
    assert all(k.startswith(prefix) for k in keys), keys
    return {k.removeprefix(prefix) for k in keys}


def test_links_of_the_star_and_the_mesh():
    """The star links the hub to each leaf only; the mesh links every pair."""
    assert host_links(spec_of(STAR)) == {"nuc": {"base", "laptop"}, "base": {"nuc"}, "laptop": {"nuc"}}
    assert host_links(spec_of(MESH)) == {
        "nuc": {"base", "laptop"},
        "base": {"nuc", "laptop"},
        "laptop": {"nuc", "base"},
    }


def test_flows_are_the_cross_host_wires_their_acks_and_presence():
    """A data flow per cross-host wire (producer -> reader), its ack back, and presence and status
    from every host to every other; wires within a host (none here) and unread outputs are not flows."""
    spec = spec_of(STAR)
    data = {(f.key.removeprefix("rover/star/"), f.src, f.dst) for f in flows(spec) if f.messages == ("put",)}
    assert data == {
        ("tick/imu", "nuc", "base"),
        ("_ack/pass/imu", "base", "nuc"),
        ("btick/silent", "base", "nuc"),
        ("_ack/watch/imu", "nuc", "base"),
        ("pass/imu", "base", "laptop"),
        ("_ack/record/imu", "laptop", "base"),
        ("tick/silent", "nuc", "laptop"),
        ("_ack/record/silent", "laptop", "nuc"),
    }
    others = {(f.key.removeprefix("rover/star/"), f.src, f.dst, f.messages) for f in flows(spec)} - {
        (k, s, d, ("put",)) for k, s, d in data
    }
    assert others == {(f"_hosts/{a}/**", a, b, ("put", "liveliness_token")) for a in HOSTS for b in HOSTS if a != b} | {
        (f"_status/{a}", a, b, ("reply", "declare_queryable")) for a in HOSTS for b in HOSTS if a != b
    }


def test_access_control_denies_by_default_and_binds_subjects_to_certificate_names(spec):
    """Enabled, default deny, one TLS subject per linked host (its common name is the host name)
    and the monitor's; nobody else, so a leaf names only its hub in the star."""
    for host in HOSTS:
        conf = access_control(spec, host)
        assert conf["enabled"] is True and conf["default_permission"] == "deny"
        linked = sorted(host_links(spec)[host])
        assert conf["subjects"] == [
            *({"id": f"host-{o}", "cert_common_names": [o], "link_protocols": ["tls"]} for o in linked),
            {"id": MONITOR, "cert_common_names": [MONITOR], "link_protocols": ["tls"]},
        ]
        assert all(r["permission"] == "allow" for r in conf["rules"])
    if spec.name == "star":
        assert [s["id"] for s in access_control(spec, "base")["subjects"]] == ["host-nuc", MONITOR]


def test_rule_ids_are_unique_and_every_reference_resolves(spec):
    """Rule, subject and policy ids are unique; every policy names existing rules and subjects and
    every rule is used; one policy per subject."""
    for host in HOSTS:
        conf = access_control(spec, host)
        for kind in ("rules", "subjects", "policies"):
            ids = [item["id"] for item in conf[kind]]
            assert len(ids) == len(set(ids)), (host, kind, ids)
        rule_ids = {r["id"] for r in conf["rules"]}
        subject_ids = {s["id"] for s in conf["subjects"]}
        used = [rid for p in conf["policies"] for rid in p["rules"]]
        assert set(used) == rule_ids and len(used) == len(rule_ids)
        assert sorted(s for p in conf["policies"] for s in p["subjects"]) == sorted(subject_ids)


def test_every_key_expression_is_valid_for_zenoh(spec):
    """zenoh.KeyExpr accepts every key expression of every rule (it raises on an invalid one)."""
    for host in HOSTS:
        for rule in access_control(spec, host)["rules"]:
            assert rule["key_exprs"], rule
            for key in rule["key_exprs"]:
                assert str(zenoh.KeyExpr(key)) == key
                assert key.startswith(f"rover/{spec.name}/")


def test_on_the_hub_base_may_put_its_read_outputs_acks_and_presence_only():
    """On nuc, base may put exactly: its outputs someone elsewhere reads (pass/imu for the laptop,
    btick/silent for nuc), the ack of its own reader (pass acking tick/imu) and its presence; never a
    nuc-owned key, nor btick/imu that nobody reads."""
    conf = access_control(spec_of(STAR), "nuc")
    allowed = short("star", rule_keys(conf, "base", "ingress", "put"))
    assert allowed == {"pass/imu", "btick/silent", "_ack/pass/imu", "_hosts/base/**"}
    assert short("star", rule_keys(conf, "base", "ingress", "liveliness_token")) == {"_hosts/base/**"}
    assert short("star", rule_keys(conf, "base", "ingress", "reply")) == {"_status/base"}
    assert short("star", rule_keys(conf, "base", "ingress", "declare_queryable")) == {"_status/base"}
    assert not rule_keys(conf, "base", "ingress", "delete")


def test_the_hub_sends_base_only_what_base_reads_plus_what_it_relays():
    """nuc's egress puts to base: tick/imu (pass reads it), nuc's ack of btick/silent, the laptop's
    ack of pass/imu (relayed), and nuc's and the laptop's presence; not tick/silent (only the laptop
    reads it), nor the laptop's ack of tick/silent (that goes to nuc)."""
    conf = access_control(spec_of(STAR), "nuc")
    sent = short("star", rule_keys(conf, "base", "egress", "put"))
    assert sent == {"tick/imu", "_ack/watch/imu", "_ack/record/imu", "_hosts/nuc/**", "_hosts/laptop/**"}
    assert "tick/silent" not in sent and "_ack/record/silent" not in sent


def test_the_hub_relays_base_to_laptop_and_the_laptop_accepts_it_from_the_hub():
    """pass/imu (base -> laptop) crosses base->nuc and nuc->laptop: allowed as nuc's ingress from
    base and egress to the laptop, and as the laptop's ingress from nuc (the laptop must accept
    base's keys from nuc, its only link); base's presence is relayed the same way, and the laptop's
    subscription to pass/imu may go to nuc and on to base."""
    spec = spec_of(STAR)
    nuc, laptop, base = (access_control(spec, h) for h in ("nuc", "laptop", "base"))
    assert "rover/star/pass/imu" in rule_keys(nuc, "base", "ingress", "put")
    assert short("star", rule_keys(nuc, "laptop", "egress", "put")) == {
        "tick/silent",
        "pass/imu",
        "_hosts/nuc/**",
        "_hosts/base/**",
    }
    assert short("star", rule_keys(laptop, "nuc", "ingress", "put")) == {
        "tick/silent",
        "pass/imu",
        "_hosts/nuc/**",
        "_hosts/base/**",
    }
    assert "rover/star/pass/imu" in rule_keys(laptop, "nuc", "egress", "declare_subscriber")
    assert "rover/star/pass/imu" in rule_keys(nuc, "laptop", "ingress", "declare_subscriber")
    assert "rover/star/pass/imu" in rule_keys(nuc, "base", "egress", "declare_subscriber")
    assert "rover/star/pass/imu" in rule_keys(base, "nuc", "ingress", "declare_subscriber")
    assert "rover/star/_ack/record/imu" in rule_keys(base, "nuc", "ingress", "put")
    assert "rover/star/tick/imu" not in rule_keys(laptop, "nuc", "ingress", "put")


def test_each_sides_egress_is_the_other_sides_ingress(spec):
    """For every link and message kind, what X sends to Y is what Y accepts from X (a one-sided rule
    would drop the traffic on the other end)."""
    confs = {h: access_control(spec, h) for h in HOSTS}
    links = host_links(spec)
    messages = {m for c in confs.values() for r in c["rules"] for m in r["messages"]}
    assert {"put", "declare_subscriber", "liveliness_token", "reply", "query"} <= messages
    for a in HOSTS:
        for b in links[a]:
            for message in messages:
                assert rule_keys(confs[a], b, "egress", message) == rule_keys(confs[b], a, "ingress", message), (
                    a,
                    b,
                    message,
                )


def test_in_the_mesh_the_third_host_may_relay():
    """Every simple path counts: base -> laptop data may also go through nuc, nuc -> laptop data
    through base, and the laptop's ack to base through nuc; nothing goes back toward its producer."""
    spec = spec_of(MESH)
    table = {edge: {f.key.removeprefix("rover/mesh/") for f in fs} for edge, fs in carried(spec).items()}
    assert "pass/imu" in table[("base", "laptop")]  # direct
    assert "pass/imu" in table[("base", "nuc")] and "pass/imu" in table[("nuc", "laptop")]  # relayed by nuc
    assert "tick/silent" in table[("nuc", "base")] and "tick/silent" in table[("base", "laptop")]  # relayed by base
    assert "_ack/record/imu" in table[("laptop", "nuc")] and "_ack/record/imu" in table[("nuc", "base")]
    assert "pass/imu" not in table[("nuc", "base")] and "pass/imu" not in table[("laptop", "nuc")]
    assert "tick/silent" not in table[("laptop", "nuc")] and "tick/silent" not in table[("laptop", "base")]
    base = access_control(spec, "base")
    assert "rover/mesh/tick/silent" in rule_keys(base, "nuc", "ingress", "put")
    assert "rover/mesh/tick/silent" in rule_keys(base, "laptop", "egress", "put")
    assert "rover/mesh/tick/imu" not in rule_keys(base, "laptop", "egress", "put")  # base is its only reader


def test_in_the_star_nothing_is_relayed_by_a_leaf():
    """In the star a leaf carries only its own flows out and flows for itself in."""
    spec = spec_of(STAR)
    for (src, dst), fs in carried(spec).items():
        if src in ("base", "laptop"):
            assert all(f.src == src for f in fs), (src, dst)
        if dst in ("base", "laptop"):
            assert all(f.dst == dst for f in fs), (src, dst)


def test_the_monitor_may_only_query_status_and_get_replies(spec):
    """The monitor's policy: query in, reply and declare_queryable out, on rover/<p>/_status/** only;
    no host rule applies to it."""
    status = f"rover/{spec.name}/_status/**"
    for host in HOSTS:
        conf = access_control(spec, host)
        [policy] = [p for p in conf["policies"] if MONITOR in p["subjects"]]
        assert policy["subjects"] == [MONITOR]
        rules = [r for r in conf["rules"] if r["id"] in policy["rules"]]
        assert sorted((tuple(r["messages"]), tuple(r["flows"]), tuple(r["key_exprs"])) for r in rules) == [
            (("query",), ("ingress",), (status,)),
            (("reply", "declare_queryable"), ("egress",), (status,)),
        ]


def test_describe_lists_each_hosts_rules():
    """`rover check --security` text: a header, then per host its rules with short keys."""
    spec = spec_of(STAR)
    text = describe(spec).splitlines()
    assert text[0].startswith(f"access control of pipeline {spec.name!r} (mutual TLS; default: deny")
    assert [line for line in text if line.startswith("host ")] == ["host nuc:", "host base:", "host laptop:"]
    nuc = text[text.index("host nuc:") + 1 : text.index("host base:")]
    assert "  put from base: _ack/pass/imu, _hosts/base/**, btick/silent, pass/imu" in nuc
    assert "  query from monitor: _status/**" in nuc
    assert "  reply/declare_queryable to monitor: _status/**" in nuc


def test_zenoh_accepts_the_generated_configuration_and_opens_a_session(spec):
    """Each host's access_control goes into a zenoh.Config and a peer session opens and closes with it
    (Zenoh validates the rules, e.g. that every rule a policy names exists, when it opens)."""
    for host in HOSTS:
        conf = zenoh.Config()
        conf.insert_json5("access_control", json.dumps(access_control(spec, host)))
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("listen/endpoints", "[]")
        conf.insert_json5("connect/endpoints", "[]")
        session = zenoh.open(conf)
        session.close()


def test_zenoh_refuses_a_broken_policy_so_the_open_test_means_something(spec):
    """The same configuration with a policy naming a missing rule does not open."""
    bad = access_control(spec, "nuc")
    bad["policies"][0]["rules"].append("no-such-rule")
    conf = zenoh.Config()
    conf.insert_json5("access_control", json.dumps(bad))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    with pytest.raises(zenoh.ZError, match="no-such-rule"):
        zenoh.open(conf).close()


def test_in_the_shipped_pipeline_raw_csi_never_leaves_the_nuc():
    """The default placement (docs/security.md): no rule of any host names replay/csi, and
    preint/odometry goes base -> nuc -> laptop, so nuc may put it toward the laptop."""
    spec, problems = parse(read_document(Path(rover.__file__).parent / "pipeline.yaml"))
    assert problems == []
    keys = {k for h in spec.hosts for r in access_control(spec, h)["rules"] for k in r["key_exprs"]}
    assert "rover/rover/replay/imu" in keys  # the placement still sends some of replay's outputs across
    assert not any("replay/csi" in k for k in keys)
    nuc = access_control(spec, "nuc")
    assert "rover/rover/preint/odometry" in rule_keys(nuc, "base", "ingress", "put")
    assert "rover/rover/preint/odometry" in rule_keys(nuc, "laptop", "egress", "put")

"""Loading pipeline files: positions, typed `${var}` substitution, command-line values."""

from __future__ import annotations

from rover.pipeline.spec import parse
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

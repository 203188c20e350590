"""A host's report of its operators (rover/runtime/host_report.py): what it writes is what it reads,
and anything else from the network is refused naming the part."""

from __future__ import annotations

import json

import pytest

from rover.operator import OperatorCounts, OperatorProfile
from rover.runtime import host_report
from rover.runtime.host_report import HostReport, ReportError


def sample() -> HostReport:
    counts = {
        "slam": OperatorCounts({"aoa": 12, "odometry": 11}, {"pose": 11}, {"aoa:without an epoch": 1}),
        "record": OperatorCounts({"pose": 11}, {}, {}),
    }
    profile = {"slam": OperatorProfile(handler_s=1.5, idle_s=0.25, cpu_s=1.4), "record": OperatorProfile()}
    return HostReport(counts, profile)


def test_a_report_reads_back_as_written():
    assert host_report.decode(host_report.encode(sample())) == sample()


def good() -> dict:
    return json.loads(host_report.encode(sample()))


NO_COUNTS: dict[str, dict[str, int]] = {"received": {}, "sent": {}, "dropped": {}}


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ({"x": {}}, "operator 'x': no counts"),
        ({"x": {"counts": {"received": {"a": -1}}}}, "x.received: expected counts"),
        ({"x": {"counts": {"received": {"a": True}}}}, "x.received: expected counts"),
        ({"x": {"counts": NO_COUNTS, "profile": {"cpu_s": 1}}}, "operator 'x': a profile has the fields"),
    ],
    ids=["no counts", "negative count", "boolean count", "profile fields"],
)
def test_a_bad_operator_entry_is_refused_naming_it(extra, message):
    with pytest.raises(ReportError, match=message):
        host_report.decode(json.dumps(good() | extra).encode())


@pytest.mark.parametrize(("payload", "message"), [(b"\xff", "not UTF-8 JSON"), (b"[1, 2]", "not a JSON object")])
def test_a_report_that_is_not_a_json_object_is_refused(payload, message):
    with pytest.raises(ReportError, match=message):
        host_report.decode(payload)


def test_a_profile_with_a_negative_time_is_refused():
    doc = good()
    doc["slam"]["profile"]["cpu_s"] = -1.0
    with pytest.raises(ReportError, match="operator 'slam': profile times are seconds of at least 0"):
        host_report.decode(json.dumps(doc).encode())

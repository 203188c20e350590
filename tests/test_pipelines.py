"""The pipelines shipped in pipelines/ pass the same checks as a user's file (operators, params,
wiring, types, hosts) and are drawn by `rover graph`."""

from __future__ import annotations

from pathlib import Path

import pytest

from rover.cli.registry import BUILTINS
from rover.operator import Source
from rover.pipeline import graph
from rover.pipeline.validation import load_and_check

PIPELINES = sorted((Path(__file__).resolve().parent.parent / "pipelines").glob("*.yaml"))


def test_there_are_shipped_pipelines():
    assert [p.name for p in PIPELINES] == ["live.yaml"]


@pytest.mark.parametrize("path", PIPELINES, ids=lambda p: p.name)
def test_a_shipped_pipeline_checks_and_draws(path):
    pipeline = load_and_check(path, BUILTINS)
    assert pipeline.hosts_in_use() == ["base", "laptop", "nuc"]
    assert "subgraph" in graph.mermaid(pipeline)


def test_the_live_pipeline_reads_the_papers_devices_on_their_hosts():
    """The NUC carries the NIC (netlink, channel hops) and the IMU, the base the Create 2, the
    laptop the method; every source is a live one."""
    pipeline = load_and_check(PIPELINES[0], BUILTINS)
    placed = {n.spec.uses: n.spec.host for n in pipeline.nodes.values()}
    assert placed["csi_netlink"] == placed["channel_hop"] == placed["microstrain_imu"] == "nuc"
    assert placed["create2"] == "base" and placed["slam"] == "laptop"
    sources = [n for n in pipeline.nodes.values() if not n.spec.inputs and n.spec.uses != "rig_source"]
    assert sources and all(issubclass(n.cls, Source) and n.cls.is_live(n.params) for n in sources), sources

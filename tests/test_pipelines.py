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


def test_the_docs_ros2_base_variant_checks(tmp_path):
    """docs/live.md's `odom` block for a ROS 2 base, put in place of the Create 2's, passes the checks."""
    docs = (PIPELINES[0].parent.parent / "docs" / "live.md").read_text()
    snippet = docs.split("## A ROS 2 base", 1)[1].split("```yaml\n", 1)[1].split("```", 1)[0]
    text = PIPELINES[0].read_text()
    create2 = '  odom:\n    uses: create2\n    host: base\n    params: {port: "${base_port}"}\n'
    assert text.count(create2) == 1
    variant = tmp_path / "live-ros2-base.yaml"
    variant.write_text(text.replace(create2, snippet))
    pipeline = load_and_check(variant, BUILTINS)
    odom = pipeline.nodes["odom"]
    assert odom.spec.uses == "ros2_subscribe" and odom.spec.host == "base"
    assert odom.ports.outputs["odom"].type == "nav_msgs/msg/Odometry"

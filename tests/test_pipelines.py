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


HOSTS = {"bearings.yaml": [], "live.yaml": ["base", "laptop", "nuc"], "ros2.yaml": []}
"""the hosts each shipped pipeline places its operators on ([]: one machine, the one with the NIC)"""


def shipped(name: str) -> Path:
    return next(p for p in PIPELINES if p.name == name)


def test_there_are_shipped_pipelines():
    assert [p.name for p in PIPELINES] == sorted(HOSTS)


@pytest.mark.parametrize("path", PIPELINES, ids=lambda p: p.name)
def test_a_shipped_pipeline_checks_and_draws(path):
    pipeline = load_and_check(path, BUILTINS)
    assert pipeline.hosts_in_use() == HOSTS[path.name]
    drawn = graph.mermaid(pipeline)
    assert drawn.startswith("flowchart") and ("subgraph" in drawn) == bool(HOSTS[path.name])


def test_the_ros2_pipeline_takes_the_robots_topics_and_gives_back_what_ros_tools_read():
    """pipelines/ros2.yaml: the IMU and odometry from the robot's graph, the NIC's CSI, and /tf,
    /tf_static (latched), the pose with covariance, the tags' markers and the path published."""
    pipeline = load_and_check(shipped("ros2.yaml"), BUILTINS)
    robot, publish = pipeline.nodes["robot"], pipeline.nodes["publish"]
    assert {p: o.type for p, o in robot.ports.outputs.items()} == {
        "imu": "sensor_msgs/msg/Imu",
        "odom": "nav_msgs/msg/Odometry",
    }
    topics = {entry["topic"]: entry for entry in publish.spec.params["topics"].values()}
    assert sorted(topics) == ["/rover/path", "/rover/pose", "/rover/tags", "/tf", "/tf_static"]
    assert topics["/tf_static"]["durability"] == "transient_local"
    assert topics["/rover/pose"]["type"] == "geometry_msgs/msg/PoseWithCovarianceStamped"
    assert pipeline.nodes["preint"].spec.inputs["imu"].text == "robot/imu"
    assert pipeline.nodes["slam"].spec.inputs["wheel"].text == "robot/odom"


def test_the_live_pipeline_reads_the_papers_devices_on_their_hosts():
    """The NUC carries the NIC (netlink, channel hops) and the IMU, the base the Create 2, the
    laptop the method; every source is a live one."""
    pipeline = load_and_check(shipped("live.yaml"), BUILTINS)
    placed = {n.spec.uses: n.spec.host for n in pipeline.nodes.values()}
    assert placed["csi_netlink"] == placed["channel_hop"] == placed["microstrain_imu"] == "nuc"
    assert placed["create2"] == "base" and placed["slam"] == "laptop"
    sources = [n for n in pipeline.nodes.values() if not n.spec.inputs and n.spec.uses != "rig_source"]
    assert sources and all(issubclass(n.cls, Source) and n.cls.is_live(n.params) for n in sources), sources


def test_the_docs_ros2_base_variant_checks(tmp_path):
    """docs/live.md's `odom` block for a ROS 2 base, put in place of the Create 2's, passes the checks."""
    docs = (shipped("live.yaml").parent.parent / "docs" / "live.md").read_text()
    snippet = docs.split("## A ROS 2 base", 1)[1].split("```yaml\n", 1)[1].split("```", 1)[0]
    text = shipped("live.yaml").read_text()
    create2 = '  odom:\n    uses: create2\n    host: base\n    params: {port: "${base_port}"}\n'
    assert text.count(create2) == 1
    variant = tmp_path / "live-ros2-base.yaml"
    variant.write_text(text.replace(create2, snippet))
    pipeline = load_and_check(variant, BUILTINS)
    odom = pipeline.nodes["odom"]
    assert odom.spec.uses == "ros2_subscribe" and odom.spec.host == "base"
    assert odom.ports.outputs["odom"].type == "nav_msgs/msg/Odometry"

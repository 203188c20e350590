"""`rover graph`: Mermaid and DOT with hosts as subgraphs and message types on the edges."""

from __future__ import annotations

from helpers import ROOT, run_rover


def test_mermaid_of_the_default_pipeline():
    proc = run_rover("graph", str(ROOT / "pipeline.yaml"))
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert out.startswith("flowchart LR")
    assert "subgraph nuc[host nuc]" in out and "subgraph laptop[host laptop]" in out
    assert 'replay -- "imu → imu<br/>sensor_msgs/Imu" --> preint' in out and "subgraph base[host base]" in out


def test_dot_of_the_default_pipeline():
    proc = run_rover("graph", "--format", "dot")
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert out.startswith('digraph "rover" {') and out.rstrip().endswith("}")
    assert 'subgraph "cluster_nuc"' in out
    assert '"replay" -> "sweep" [label="csi → frames\\nrover_msgs/CsiFrame"];' in out

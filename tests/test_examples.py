"""examples/ and the README's snippets run as written: the own operator, the custom pipeline, the
Python API script, and the README's pipeline and operator (the same text as the example's file)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
from helpers import LAP, ROOT, read_bag, run_rover, write_imu_dataset

from rover.messages import deserialize

EXAMPLES = ROOT / "examples"
README = (ROOT / "README.md").read_text()


def readme_block(language: str) -> str:
    """The README's one fenced block in `language`."""
    blocks = re.findall(rf"^```{language}\n(.*?)^```", README, flags=re.S | re.M)
    assert len(blocks) == 1, f"README.md has {len(blocks)} {language} blocks"
    return blocks[0]


def test_the_readmes_operator_is_the_examples_file():
    assert readme_block("python") == (EXAMPLES / "own_operator" / "mylab" / "filters.py").read_text()


def test_the_readmes_pipeline_is_valid(tmp_path):
    path = tmp_path / "pipeline.yaml"
    path.write_text(readme_block("yaml"))
    proc = run_rover("check", str(path))
    assert proc.returncode == 0, proc.stderr


def test_own_operator_pipeline_scales_the_yaw_rate(tmp_path):
    dataset = write_imu_dataset(tmp_path / "imu.mcap", 400, odom_every=0)
    env = dict(os.environ, PYTHONPATH=str(EXAMPLES / "own_operator"))
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "rover.cli", "run", str(EXAMPLES / "own_operator" / "pipeline.yaml")]
        + ["--dataset", str(dataset), "--output", str(out)],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    before = [deserialize(data, "sensor_msgs/msg/Imu") for topic, _, data in read_bag(dataset)]
    after = [deserialize(data, "sensor_msgs/msg/Imu") for topic, _, data in read_bag(out / "imu.mcap")]
    assert len(after) == len(before) == 400
    assert [m.angular_velocity.z for m in after] == [2.0 * m.angular_velocity.z for m in before]


@pytest.mark.slow
def test_aoa_only_pipeline_records_every_tags_bearings(tmp_path, simulated):
    out = tmp_path / "aoa"
    proc = run_rover("run", str(EXAMPLES / "aoa_only.yaml"), "--dataset", str(simulated(*LAP)), "--output", str(out))
    assert proc.returncode == 0, proc.stderr
    aoas = [
        deserialize(data, "rover_msgs/msg/Aoa")
        for topic, _, data in read_bag(out / "results.mcap")
        if topic == "/rover/aoa"
    ]
    assert {a.tag_id for a in aoas} == {1, 2, 3, 4}
    assert all(len(a.candidate_angles_rad) >= 1 for a in aoas)


@pytest.mark.slow
def test_python_api_script_prints_each_tags_bearings(simulated):
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / "aoa_from_dataset.py"), str(simulated(*LAP)), "--seconds", "20"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert [line.split(":")[0] for line in proc.stdout.splitlines()[1:]] == ["tag 1", "tag 2", "tag 3", "tag 4"]


def test_python_api_script_refuses_a_dataset_without_a_rig(tmp_path):
    dataset = write_imu_dataset(tmp_path / "imu.mcap", 10)
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / "aoa_from_dataset.py"), str(dataset)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"{dataset}: no rig description (rover.setup): convert it with --setup"


def test_the_readmes_operator_line_added_to_the_default_pipeline_checks(tmp_path):
    """The README's `In the pipeline:` line, added as it is under the default pipeline's operators
    (on one machine and split over its three hosts), passes `rover check` with mylab importable."""
    (line,) = re.findall(r"^In the pipeline: `(scale: \{.*\})`", README, flags=re.M)
    text = (ROOT / "rover" / "pipeline.yaml").read_text()
    assert "\noperators:\n" in text
    path = tmp_path / "pipeline.yaml"
    path.write_text(text.replace("\noperators:\n", f"\noperators:\n  {line}\n", 1))
    env = dict(os.environ, PYTHONPATH=str(EXAMPLES / "own_operator"))
    for host in ([], ["--host", "nuc"]):
        proc = subprocess.run(
            [sys.executable, "-m", "rover.cli", "check", str(path), *host], capture_output=True, text=True, env=env
        )
        assert proc.returncode == 0, proc.stderr
